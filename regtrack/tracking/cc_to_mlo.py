"""View -> view: a point marked on one real mammogram predicted as a curve on the other.

A point ``r`` of the real source mammogram (e.g. CC) is taken back through its
registration to the virtual image plane, ``v = n_v + R(-theta_p)(r - n_p)``.  Every
material point of the compressed source configuration that projects onto ``v`` lies on
one ray (along the plate normal, or towards the X-ray source):

.. math:: \\ell(h) = o + X(h)\\, e_x + Y(h)\\, e_{down} + h\\, n, \\qquad h_{min} \\le h \\le h_{max}

The ray is sampled every ``ray_step_mm``; each sample inside the *deformed* source mesh
is located there (element ``e``, barycentric ``lambda``).  The same material point sits
at ``sum_k lambda_k x^{tgt}_{e,k}`` in the compressed target configuration (e.g. MLO),
which is projected and aligned into the real target mammogram.  The prediction is this
curve segment: the lesion lies somewhere along it.  Its material points are also
carried to the reference (MRI) configuration, so when the MRI lesion is known the most
likely point is the ray sample whose reference position is closest to it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from regtrack.errors import TrackingError
from regtrack.model.types import BreastModel
from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.locate import TetLocator
from regtrack.tracking.uncertainty import inplane_shift
from regtrack.tracking.viewmap import ViewMap

log = logging.getLogger(__name__)


@dataclass
class SegmentPrediction:
    """The curve predicted in the target view for a point marked in the source view.

    Attributes
    ----------
    source_view, target_view : str
    source_mm : (2,) real canonical frame of the source view (mm)
    source_px : (2,) or None, (row, col) in the source DICOM grid
    heights_mm : (H,) height of each ray sample above the source lower plate (mm)
    reference_mm : (H, 3) material points in the reference (MRI) configuration (model frame)
    polyline_mm : (H, 2) predicted curve in the real target frame (mm)
    polyline_px : (H, 2) or None, (row, col) in the target DICOM grid
    sigma_mm : (H,) 1-sigma radius of each vertex (mm; NaN without the target view's
        uncertainty model)
    parts : list of (start, stop) index ranges of continuous runs inside the breast
    most_likely : dict or None
        ``{"index", "xy_mm", "px_rc", "height_mm", "reference_distance_mm"}``: the sample
        closest (in the MRI configuration) to the known lesion.
    truth_distance_mm : float or None
        Distance from the true target position to the curve (mm).
    """

    source_view: str
    target_view: str
    source_mm: np.ndarray
    source_px: np.ndarray | None
    heights_mm: np.ndarray
    reference_mm: np.ndarray
    polyline_mm: np.ndarray
    polyline_px: np.ndarray | None
    sigma_mm: np.ndarray
    parts: list[tuple[int, int]] = field(default_factory=list)
    most_likely: dict | None = None
    truth_distance_mm: float | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def length_mm(self) -> float:
        """Arc length of the predicted curve in the target image (mm), all parts."""
        return float(sum(np.linalg.norm(np.diff(self.polyline_mm[a:b], axis=0), axis=1).sum()
                         for a, b in self.parts))

    @property
    def thickness_mm(self) -> float:
        """Extent of the ray inside the compressed source breast along the plate normal (mm;
        the local compressed thickness for the orthogonal projection)."""
        step = np.diff(self.heights_mm).mean() if len(self.heights_mm) > 1 else 0.0
        return float(sum((b - a - 1) * step for a, b in self.parts))

    def distance_to(self, xy_mm) -> float:
        """Distance (mm) from a real target-frame point to the curve."""
        from shapely.geometry import LineString, MultiLineString, Point

        lines = [self.polyline_mm[a:b] for a, b in self.parts]
        lines = [ln if len(ln) > 1 else np.vstack([ln, ln]) for ln in lines]
        geom = MultiLineString(lines) if len(lines) > 1 else LineString(lines[0])
        return float(geom.distance(Point(np.asarray(xy_mm, float))))

    def to_dict(self, *, max_vertices: int = 400) -> dict:
        step = max(1, int(np.ceil(len(self.polyline_mm) / max_vertices)))
        keep = np.unique(np.r_[np.arange(0, len(self.polyline_mm), step),
                               [b - 1 for _, b in self.parts], [a for a, _ in self.parts]])
        return {
            "source_view": self.source_view, "target_view": self.target_view,
            "source_xy_mm": self.source_mm.tolist(),
            "source_px_rc": None if self.source_px is None else self.source_px.tolist(),
            "length_mm": self.length_mm, "ray_length_in_breast_mm": self.thickness_mm,
            "parts": [list(p) for p in self.parts],
            "vertices_kept_every": step,
            "polyline_mm": self.polyline_mm[keep].tolist(),
            "polyline_px_rc": None if self.polyline_px is None else self.polyline_px[keep].tolist(),
            "sigma_mm": self.sigma_mm[keep].tolist(),
            "heights_mm": self.heights_mm[keep].tolist(),
            "reference_model_mm": self.reference_mm[keep].tolist(),
            "most_likely": self.most_likely, "truth_distance_mm": self.truth_distance_mm,
            "notes": self.notes,
        }


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of the runs of True in a 1-D bool array."""
    d = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _check_inside_real(src: ViewMap, xy: np.ndarray, label: str) -> None:
    real = src.real
    if real is None or real.breast_contour is None or len(real.breast_contour) < 3:
        return
    from shapely.geometry import Point

    from regtrack.registration.geometry import polygon

    poly = polygon(real.breast_contour)
    if not poly.buffer(1.0).covers(Point(*xy)):
        raise TrackingError(
            f"{label} lies outside the breast on the real {src.view} mammogram "
            f"({real.source or 'image'}; {poly.exterior.distance(Point(*xy)):.1f} mm from the "
            "breast contour): mark a point inside the breast, as (row, col) of the DICOM "
            "pixel grid")


def most_likely(seg: SegmentPrediction, lesion_reference_mm, *, truth_mm=None,
                lesion: str | None = None) -> dict:
    """Set ``seg.most_likely``: the ray sample whose reference (MRI) position is closest
    to the known lesion ``lesion_reference_mm`` (model frame, mm)."""
    d = np.linalg.norm(seg.reference_mm - np.asarray(lesion_reference_mm, float), axis=1)
    k = int(np.argmin(d))
    xy = seg.polyline_mm[k]
    seg.most_likely = {
        "index": k, "xy_mm": xy.tolist(),
        "px_rc": None if seg.polyline_px is None else seg.polyline_px[k].tolist(),
        "height_mm": float(seg.heights_mm[k]), "sigma_mm": float(seg.sigma_mm[k]),
        "reference_distance_mm": float(d[k]), "lesion": lesion,
        "truth_distance_mm": None if truth_mm is None else
        float(np.linalg.norm(xy - np.asarray(truth_mm, float)))}
    return seg.most_likely


def track_view_point(model: BreastModel, src: ViewMap, dst: ViewMap, point, *,
                     pixels: bool = True, config: TrackingConfig | None = None,
                     lesion_reference_mm=None, truth_mm=None,
                     src_locator: TetLocator | None = None) -> SegmentPrediction:
    """Curve segment in view ``dst`` of the material under ``point`` of view ``src``.

    Parameters
    ----------
    model : BreastModel
        Reference mesh (its ``tets`` and ``points``).
    src, dst : ViewMap
        Source and target views (e.g. CC and MLO) of the same model.
    point : (2,) float
        ``(row, col)`` of the source DICOM grid when ``pixels`` (default), else ``(x, y)``
        mm of the source's real canonical frame.
    lesion_reference_mm : (3,) float, optional
        Known lesion (e.g. the MRI tumour centroid), model frame, reference configuration.
    truth_mm : (2,) float, optional
        True position in the real target frame (mm): its distance to the curve is reported.
    src_locator : TetLocator, optional
        Locator on the deformed source mesh (re-used between calls).

    Raises
    ------
    TrackingError
        Point outside the real breast, or a ray that misses the compressed model.
    """
    cfg = config or TrackingConfig()
    p = np.asarray(point, float).reshape(-1)
    if p.shape != (2,) or not np.isfinite(p).all():
        raise TrackingError(f"{src.view} point {list(point)} must be two finite numbers (row col)")
    if pixels:
        if src.pixels is None:
            raise TrackingError(f"the {src.view} view has no pixel grid (not read from a DICOM); "
                                "give the point in mm")
        shape = src.pixels.shape
        if shape is not None and not (0 <= p[0] <= shape[0] - 1 and 0 <= p[1] <= shape[1] - 1):
            raise TrackingError(f"{src.view} point (row {p[0]:g}, col {p[1]:g}) lies outside the "
                                f"{shape[0]}x{shape[1]} px image {src.pixels.source}; give "
                                "(row, col) of the DICOM pixel grid")
        xy = src.pixels.px_to_mm(p)
        label = f"{src.view} point (row {p[0]:g}, col {p[1]:g})"
    else:
        xy = p
        label = f"{src.view} point (x {p[0]:.1f}, y {p[1]:.1f} mm)"
    _check_inside_real(src, xy, label)
    v = src.inplane.to_virtual(xy)
    h0, h1 = src.height_range()
    heights = np.arange(h0 - cfg.ray_step_mm, h1 + 2 * cfg.ray_step_mm, cfg.ray_step_mm)
    ray = src.ray(v, heights)
    loc_ = src_locator or TetLocator(src.positions, model.tets)
    loc = loc_.locate(ray)
    parts = _runs(loc.inside)
    if not parts:
        raise TrackingError(f"{label}: the ray through the compressed {src.view} model misses "
                            "the simulated breast (the point may lie in tissue the MRI model "
                            "does not contain, e.g. behind its chest-wall cut); mark a point "
                            "closer to the nipple")
    keep = loc.inside
    loc = loc.subset(keep)
    idx = np.cumsum(keep) - 1
    parts = [(int(idx[a]), int(idx[b - 1]) + 1) for a, b in parts]
    tgt = loc.interpolate(model.tets, dst.positions)
    ref = loc.interpolate(model.tets, model.points)
    xy_t = dst.to_real(tgt)
    sigma = np.full(len(xy_t), np.nan)
    if dst.uncertainty is not None:
        shift = inplane_shift(dst.frame, ref, tgt, model.points[model.nipple],
                              dst.positions[model.nipple])
        sigma = dst.uncertainty.at(xy_t, shift)[0]
    seg = SegmentPrediction(
        src.view, dst.view, xy, p if pixels else None, heights[keep], ref, xy_t,
        None if dst.pixels is None else dst.pixels.mm_to_px(xy_t), sigma, parts)
    if len(parts) > 1:
        seg.notes.append(f"the ray leaves and re-enters the compressed breast ({len(parts)} parts)")
    if lesion_reference_mm is not None:
        most_likely(seg, lesion_reference_mm, truth_mm=truth_mm)
    if truth_mm is not None:
        seg.truth_distance_mm = seg.distance_to(truth_mm)
    log.info("%s -> %s: curve of %.1f mm (ray %.1f mm inside the breast)", src.view, dst.view,
             seg.length_mm, seg.thickness_mm)
    return seg


@dataclass
class ContourPrediction:
    """The region predicted in the target view for a contour marked in the source view:
    one curve per (resampled) contour vertex and their convex hull (mm, real target frame)."""

    segments: list[SegmentPrediction]
    region_mm: np.ndarray

    def to_dict(self) -> dict:
        return {"region_mm": self.region_mm.tolist(),
                "curves": [s.to_dict(max_vertices=50) for s in self.segments]}


def track_view_contour(model: BreastModel, src: ViewMap, dst: ViewMap, contour, *,
                       pixels: bool = True, max_vertices: int = 24,
                       config: TrackingConfig | None = None) -> ContourPrediction:
    """Curves in ``dst`` of up to ``max_vertices`` vertices of a ``src`` contour, and the
    convex hull of all of them (the region where the marked lesion can appear).

    ``contour`` is (K, 2): (row, col) of the source DICOM grid, or mm when not ``pixels``.
    """
    from shapely.geometry import MultiPoint

    c = np.asarray(contour, float)
    if c.ndim != 2 or c.shape[1] != 2 or len(c) < 1:
        raise TrackingError(f"{src.view} contour must be (K, 2) points (row, col); got shape "
                            f"{c.shape}")
    step = max(1, int(np.ceil(len(c) / max_vertices)))
    loc = TetLocator(src.positions, model.tets)
    segs = [track_view_point(model, src, dst, p, pixels=pixels, config=config, src_locator=loc)
            for p in c[::step]]
    hull = MultiPoint(np.vstack([s.polyline_mm for s in segs])).convex_hull
    region = np.asarray(getattr(hull, "exterior", hull).coords)
    return ContourPrediction(segs, region[:-1] if len(region) > 2 else region)
