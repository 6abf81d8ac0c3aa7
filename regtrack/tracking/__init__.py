"""Lesion tracking through the patient model (issue 9, ``regtrack track``).

* MRI -> mammogram: :func:`track_mri_point`, :func:`track_tumour`,
  :func:`track_points_region` (predicted position in each real view, px and mm, with an
  uncertainty radius);
* view -> view: :func:`track_view_point` (a point on the CC mammogram becomes a curve
  segment on the MLO one, and back);
* the chain model -> plate -> registration -> pixels: :class:`ViewMap`, :class:`InPlane`,
  :class:`PixelFrame`; point location: :class:`TetLocator`;
* cases: :func:`open_case` builds the view maps from the cached pipeline stages.
"""

from regtrack.tracking.cc_to_mlo import SegmentPrediction, track_view_point
from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.locate import Location, TetLocator
from regtrack.tracking.mri_to_view import (MriTrack, ViewPrediction, track_mri_point,
                                           track_points_region, track_tumour)
from regtrack.tracking.uncertainty import PredictionUncertainty, Residual
from regtrack.tracking.viewmap import InPlane, PixelFrame, ViewMap, viewmap_from_outcome
from regtrack.tracking.session import TrackingSession, open_case  # noqa: I001
from regtrack.tracking.track import TrackResult, track_case
from regtrack.tracking.figures import draw_tracking_page, report_section, write_outputs

__all__ = ["InPlane", "Location", "MriTrack", "PixelFrame", "Residual", "SegmentPrediction",
           "TetLocator", "TrackingConfig", "PredictionUncertainty", "ViewMap", "ViewPrediction",
           "track_mri_point", "track_points_region", "track_tumour",
           "track_view_point", "TrackingSession", "open_case", "viewmap_from_outcome",
           "TrackResult", "track_case", "draw_tracking_page", "report_section", "write_outputs"]
