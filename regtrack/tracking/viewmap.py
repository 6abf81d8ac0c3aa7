"""The chain from a compressed 3-D configuration to the pixels of a real mammogram.

For one view (CC or MLO) a point ``p`` of the deformed model (mm, model frame) maps to

1. plate coordinates ``(X, Y, h) = R (p - o)`` (:class:`regtrack.virtual.frames.PlateFrame`,
   rows ``e_x, e_down, n``), then the virtual image plane: ``(X, Y)`` for the orthogonal
   projection of Lapuebla-Ferri et al., or the magnified ``(X', Y')`` of a point source
   (:func:`regtrack.virtual.xray.perspective`);
2. the real mammogram's canonical frame (mm) by the registration:
   ``r = n_p + R(theta_p) (v - n_v)`` (:class:`InPlane`);
3. canonical full-resolution pixels ``(row, col) = (y / s_row, x / s_col)`` (the reader's
   convention: the centre of canonical pixel (0, 0) is at (0, 0) mm), then the DICOM's own
   pixel grid through the reader's :class:`~regtrack.imaging.mammogram.orient.Orientation`
   (flips/transposition), :class:`PixelFrame`.

Every step is invertible; :meth:`ViewMap.ray` gives the set of 3-D points that project
onto one image point (a line along the plate normal, or towards the source).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from regtrack.registration.geometry import rotation
from regtrack.tracking.uncertainty import PredictionUncertainty, Residual
from regtrack.virtual.frames import PlateFrame
from regtrack.virtual.xray import PointSource, perspective


@dataclass(frozen=True)
class InPlane:
    """Rigid in-plane registration of a virtual view on the real one (mm, degrees).

    ``r = n_p + R(theta) (v - n_v)``; ``theta_b`` / ``theta_t`` are the breast and tumour
    optima (``theta`` their mean in the paper's method; ``theta_t`` NaN when unused).
    """

    nipple: np.ndarray          # n_p, real frame (mm)
    virtual_nipple: np.ndarray  # n_v, virtual frame (mm)
    theta_deg: float
    theta_b_deg: float = float("nan")
    theta_t_deg: float = float("nan")

    @classmethod
    def from_alignment(cls, al) -> InPlane:
        """From a :class:`regtrack.registration.align.Alignment`."""
        return cls(np.asarray(al.nipple, float), np.asarray(al.virtual_nipple, float),
                   float(al.theta_p), float(al.theta_p_b), float(al.theta_p_t))

    def to_real(self, xy) -> np.ndarray:
        """(..., 2) virtual mm -> real canonical mm."""
        R = rotation(self.theta_deg)
        return (np.asarray(xy, float) - self.virtual_nipple) @ R.T + self.nipple

    def to_virtual(self, xy) -> np.ndarray:
        """(..., 2) real canonical mm -> virtual mm (inverse of :meth:`to_real`)."""
        R = rotation(self.theta_deg)
        return (np.asarray(xy, float) - self.nipple) @ R + self.virtual_nipple

    def to_dict(self) -> dict:
        def f(v):
            return None if not np.isfinite(v) else float(v)
        return {"nipple_real_mm": self.nipple.tolist(),
                "nipple_virtual_mm": self.virtual_nipple.tolist(),
                "theta_p_deg": self.theta_deg, "theta_p_b_deg": f(self.theta_b_deg),
                "theta_p_t_deg": f(self.theta_t_deg)}


@dataclass(frozen=True)
class PixelFrame:
    """Real mammogram pixels: canonical (row, col) <-> mm, and the DICOM's own grid.

    ``spacing`` is the (row, col) spacing (mm) of the full-resolution canonical image;
    ``orientation`` (optional) maps canonical pixels to the stored DICOM grid.
    """

    spacing: np.ndarray
    orientation: object = None  # regtrack.imaging.mammogram.orient.Orientation
    source: str = ""

    @classmethod
    def from_view(cls, real) -> PixelFrame | None:
        """From a real :class:`~regtrack.views.MammogramView` made by ``extract_view``
        (reads ``meta["image"]["spacing_mm"]`` and ``["orientation"]``); None if absent."""
        from regtrack.imaging.mammogram.orient import Orientation

        im = (real.meta or {}).get("image") or {}
        sp = im.get("spacing_mm")
        if sp is None:
            return None
        o = im.get("orientation")
        orient = None
        if o:
            orient = Orientation(tuple(o["source_shape"]), bool(o["transpose"]),
                                 bool(o["flip_lr"]), bool(o["flip_ud"]), o.get("rule", ""))
        return cls(np.asarray(sp, float), orient, real.source)

    def mm_to_canonical(self, xy) -> np.ndarray:
        xy = np.asarray(xy, float)
        return np.stack([xy[..., 1] / self.spacing[0], xy[..., 0] / self.spacing[1]], -1)

    def canonical_to_mm(self, rc) -> np.ndarray:
        rc = np.asarray(rc, float)
        return np.stack([rc[..., 1] * self.spacing[1], rc[..., 0] * self.spacing[0]], -1)

    def mm_to_px(self, xy) -> np.ndarray:
        """(..., 2) canonical mm -> (row, col) of the DICOM's own pixel grid."""
        rc = self.mm_to_canonical(xy)
        return rc if self.orientation is None else self.orientation.to_source_px(rc)

    def px_to_mm(self, rc) -> np.ndarray:
        """(..., 2) (row, col) of the DICOM's own pixel grid -> canonical mm."""
        rc = np.asarray(rc, float)
        if self.orientation is not None:
            rc = self.orientation.to_canonical_px(rc)
        return self.canonical_to_mm(rc)

    @property
    def shape(self) -> tuple[int, int] | None:
        """(rows, cols) of the DICOM grid, when known."""
        return None if self.orientation is None else tuple(self.orientation.source_shape)

    @property
    def mean_spacing(self) -> float:
        return float(np.mean(self.spacing))


@dataclass
class ViewMap:
    """Everything needed to carry model points into one real mammogram.

    Attributes
    ----------
    view : {"CC", "MLO"}
    positions : (N, 3) float
        Deformed (compressed) node positions of this view's simulation (mm, model frame).
    frame : PlateFrame
        Plate frame of the projection (``regtrack.virtual.project.default_frame``).
    inplane : InPlane
        Registration of the virtual view on the real one.
    pixels : PixelFrame or None
        Real image pixel frames (None: results in mm only).
    source : PointSource or None
        X-ray point source of the virtual projection (None: orthogonal, as in the paper).
    residual : Residual or None
        Aligned contour residuals (those of :attr:`uncertainty` when it is given).
    real : MammogramView or None
        The real view (for figures and the inside-the-breast check).
    uncertainty : PredictionUncertainty or None
        The uncertainty model of a prediction (:mod:`regtrack.tracking.uncertainty`);
        None: positions without a radius.
    """

    view: str
    positions: np.ndarray
    frame: PlateFrame
    inplane: InPlane
    pixels: PixelFrame | None = None
    source: PointSource | None = None
    residual: Residual | None = None
    real: object = None
    uncertainty: PredictionUncertainty | None = None

    def to_virtual(self, points) -> np.ndarray:
        """(M, 3) deformed model points (mm) -> (M, 2) virtual image plane (mm)."""
        local = self.frame.to_local(np.atleast_2d(points))
        if self.source is None:
            return local[:, :2]
        return perspective(local, self.source)[:, :2]

    def to_real(self, points) -> np.ndarray:
        """(M, 3) deformed model points (mm) -> (M, 2) real canonical frame (mm)."""
        return self.inplane.to_real(self.to_virtual(points))

    def ray(self, xy_virtual, heights) -> np.ndarray:
        """(H, 3) model points at plate heights ``heights`` (mm) that project onto ``xy_virtual``.

        Orthogonal: ``o + X e_x + Y e_down + h n``.  Point source at height ``h_s`` with
        foot ``f``: ``X = f + (X' - f) (h_s - h) / SID`` (inverse of the magnification).
        """
        h = np.asarray(heights, float)
        xy = np.asarray(xy_virtual, float).reshape(2)
        if self.source is None:
            X = np.broadcast_to(xy, (len(h), 2))
        else:
            f = np.asarray(self.source.foot, float)
            X = f + (xy - f) * ((self.source.height - h) / self.source.sid)[:, None]
        return self.frame.to_model(np.column_stack([X, h]))

    def height_range(self) -> tuple[float, float]:
        """Lowest and highest deformed node above the lower plate (mm)."""
        h = self.frame.height(self.positions)
        return float(h.min()), float(h.max())


def viewmap_from_outcome(outcome, *, config=None) -> ViewMap:
    """The :class:`ViewMap` of a pipeline :class:`~regtrack.pipeline.stages.ViewOutcome`
    (simulated positions, virtual plate frame and source, real view) with the registration
    and uncertainty model of every prediction: the breast-only registration
    (``extra["breast_alignment"]``, :func:`breast_alignment`) and
    the simulation's ``D`` with its 1-sigma (``extra["sigma_D"]``); ``config`` the
    :class:`~regtrack.tracking.config.TrackingConfig` (default: its defaults).

    For the case report: ``track_tumour(model, {o.view: viewmap_from_outcome(o) for o in
    results})`` gives the tumour's predicted position in every real view, the same as
    ``regtrack run``'s lesion prediction."""
    from regtrack.tracking.config import TrackingConfig

    extra = getattr(outcome, "extra", None) or {}
    al = extra.get("breast_alignment") or breast_alignment(outcome.alignment, outcome.real,
                                                           outcome.virtual)
    D = (outcome.sim.summary or {}).get("D")
    unc = PredictionUncertainty.from_alignment(al, outcome.real, D=D,
                                               sigma_D=float(extra.get("sigma_D", 0.0)),
                                               config=config or TrackingConfig())
    return ViewMap(outcome.view, outcome.sim.positions, outcome.virtual.frame,
                   InPlane.from_alignment(al), PixelFrame.from_view(outcome.real),
                   outcome.virtual.source, unc.residual, outcome.real, unc)


def breast_alignment(alignment, real, virtual):
    """The registration on the breast outline and nipple only (``use_tumour = false``):
    ``alignment`` itself when it already is one, else a new golden-section search."""
    from regtrack.registration import align

    if alignment.tumour_objective is None:
        return alignment
    cfg = replace(alignment.config, use_tumour=False)
    return align(real, virtual, config=cfg)
