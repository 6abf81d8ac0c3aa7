"""The 2-D view both sides of the comparison produce: :class:`MammogramView`.

A real mammogram (``regtrack.imaging.mammogram``) and a virtual one (``regtrack.virtual``)
are reduced to the same plain data so registration and metrics never need to know where
a view came from.

Canonical 2-D frame (mm)
------------------------
The standard display of a *left* breast, for both views and both sides:

* ``x`` grows to the right, from the chest wall (left edge) to the nipple: the
  posterior-to-anterior direction;
* ``y`` grows downwards (image row direction): the patient's **medial** direction for CC
  views (IHE Mammography ``PatientOrientation`` ``A\\R`` for LCC; RCC ``P\\L`` flipped to
  ``A\\L``), and the **infero-medial** direction in the plate plane for MLO views
  (``A\\FR`` / flipped ``A\\FL``).

Pixel ``(row, col)`` of ``image`` has its centre at ``(x, y) = origin + (col*sx, row*sy)``
with ``pixel_spacing = (sy, sx)`` (DICOM order: row spacing first).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

VIEWS = ("CC", "MLO")
#: Every compression the mechanics simulates: the mammographic views and the latero-medial
#: compression of the prone breast in an MR biopsy coil (no mammogram; the shipped protocol
#: ``regtrack/mechanics/data/protocols/biopsy.toml``).
SIMULATED_VIEWS = (*VIEWS, "BIOPSY")
LATERALITIES = ("L", "R")


@dataclass
class MammogramView:
    """Breast contour, tumour contour(s) and nipple of one mammographic view, in mm.

    Attributes
    ----------
    view : {"CC", "MLO"}
    laterality : {"L", "R"}
    breast_contour : (M, 2) float
        The outer skin line as an *open* polyline (mm), ordered from one chest-wall end to
        the other; the chest-wall side is not part of it.
    tumour_contours : list of (K, 2) float
        Closed polygons (mm), first point not repeated.  May be empty.
    nipple : (2,) float
        Nipple position (mm).
    image : 2-D float array or None
        Image in the canonical orientation (real: the flipped pixel data; virtual: the
        X-ray-like rendering), values in [0, 1], bright = dense.
    pixel_spacing : (2,) float
        (row, column) spacing of ``image`` (mm).
    origin : (2,) float
        (x, y) mm of the centre of pixel (0, 0).
    breast_mask : 2-D bool array or None
        Breast region on the ``image`` grid.
    source : str
        Provenance (file name or "virtual:<result>").
    meta : dict
        Extras: nipple confidence, notes on fall-backs, chest-wall line, etc.
    """

    view: str
    laterality: str
    breast_contour: np.ndarray
    nipple: np.ndarray
    tumour_contours: list[np.ndarray] = field(default_factory=list)
    image: np.ndarray | None = None
    pixel_spacing: np.ndarray = field(default_factory=lambda: np.array([1.0, 1.0]))
    origin: np.ndarray = field(default_factory=lambda: np.zeros(2))
    breast_mask: np.ndarray | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def pixel_to_mm(self, rc) -> np.ndarray:
        """Map (..., 2) pixel (row, col) to (..., 2) mm (x, y) of this frame."""
        rc = np.asarray(rc, float)
        sy, sx = self.pixel_spacing
        return np.stack([self.origin[0] + rc[..., 1] * sx, self.origin[1] + rc[..., 0] * sy], -1)

    def mm_to_pixel(self, xy) -> np.ndarray:
        """Map (..., 2) mm (x, y) to (..., 2) pixel (row, col)."""
        xy = np.asarray(xy, float)
        sy, sx = self.pixel_spacing
        return np.stack([(xy[..., 1] - self.origin[1]) / sy, (xy[..., 0] - self.origin[0]) / sx], -1)

    def to_dict(self) -> dict:
        """JSON-ready summary (contours in mm, no image)."""
        return {
            "view": self.view,
            "laterality": self.laterality,
            "nipple_mm": np.asarray(self.nipple).tolist(),
            "breast_contour_mm": np.asarray(self.breast_contour).tolist(),
            "tumour_contours_mm": [np.asarray(c).tolist() for c in self.tumour_contours],
            "pixel_spacing_mm": np.asarray(self.pixel_spacing).tolist(),
            "origin_mm": np.asarray(self.origin).tolist(),
            "source": self.source,
            "meta": self.meta,
        }
