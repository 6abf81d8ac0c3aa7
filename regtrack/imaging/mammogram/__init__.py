"""Real mammograms: DICOM reading, canonical orientation, breast segmentation, contour,
nipple and tumour extraction (issue 6, parts 1-2).

Public API::

    img = read_mammogram("cc.dcm", pixel_spacing_mm=None, view=None, laterality=None)
    view = extract_view(img, tumour_polygon_px=None, tumour_mask=None,
                        tumour_seed_px=None, nipple_px=None)   # -> regtrack.views.MammogramView
"""

from .config import MammogramConfig
from .dicom import MammogramImage, mammogram_from_array, read_mammogram
from .extract import extract_view
from .orient import Orientation
from .overlay import write_overlay
from .segment import BreastSegmentation, segment_breast

__all__ = ["MammogramConfig", "MammogramImage", "Orientation", "BreastSegmentation",
           "read_mammogram",
           "mammogram_from_array", "extract_view", "segment_breast", "write_overlay"]
