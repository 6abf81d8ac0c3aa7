"""Metrics of a real/virtual mammogram alignment.

All lengths in mm, angles in degrees, percentages in %.  The paper's metrics
(Lapuebla-Ferri et al.) are :math:`BS_{Av}`, :math:`TS_{Av}` (eqs. 4-5),
:math:`\\theta_{p,b}`, :math:`\\theta_{p,t}`, :math:`\\theta_p`, the compression degree
``D`` and the centroid distances :math:`d_T`, :math:`d_B`; per-point distance statistics
and Dice coefficients are modern complements.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from regtrack.registration import geometry as G
from regtrack.registration.align import Alignment, Objective
from regtrack.views import MammogramView


@dataclass(frozen=True)
class DistanceStats:
    """Closest-point distances (mm) between an aligned virtual and a real contour.

    ``mean`` and ``p95`` are over the virtual points' distances to the real contour;
    ``hausdorff`` is the symmetric Hausdorff distance
    :math:`\\max(\\max_v d(v, R), \\max_r d(r, V))` of the two resampled contours.
    """

    mean: float
    p95: float
    max: float
    hausdorff: float
    n_points: int


@dataclass(frozen=True)
class Metrics:
    """All metrics of one view (see :func:`compute_metrics` for the equations)."""

    view: str
    bs_av: float
    ts_av: float
    bs_av_b: float
    ts_av_t: float
    theta_p_b: float
    theta_p_t: float
    theta_p: float
    D: float | None
    d_T: float
    d_B: float
    breast_distance: DistanceStats
    tumour_distance: DistanceStats | None
    dice_breast: float
    dice_tumour: float
    evaluations_b: int
    evaluations_t: int

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN -> None)."""
        def clean(x):
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, float) and not math.isfinite(x):
                return None
            return x
        return clean(asdict(self))


def similarity_percent(obj: Objective, theta_p: float) -> float:
    """Similarity (%) of a contour pair: eqs. 4-5 of the paper.

    .. math::

        S = \\left(1 - \\frac{\\sum_i \\lVert v_i(\\theta_p) - r_{c(i)} \\rVert}
                            {\\sum_i \\lVert v_i(0) - r_{c(i)} \\rVert}\\right) \\cdot 100

    i.e. the relative reduction of the summed closest-point distance achieved by the
    rotation ``theta_p`` over the nipple superposition alone (``theta = 0``).  100 % is a
    perfect fit; 0 % no improvement; negative values a worse fit.
    """
    d0 = float(obj.distances(0.0).sum())
    dp = float(obj.distances(theta_p).sum())
    if d0 == 0.0:
        return 100.0 if dp == 0.0 else float("-inf")
    return (1.0 - dp / d0) * 100.0


def distance_stats(points: np.ndarray, contour: np.ndarray, *, closed: bool,
                   spacing: float) -> DistanceStats:
    """Distance statistics (mm) of aligned virtual contour ``points`` to ``contour``.

    ``d_i = min_{r in R} ||v_i - r||`` over the real polyline ``R``; reports the mean, the
    95th percentile, the maximum, and the symmetric Hausdorff distance between the two
    contours resampled at ``spacing`` mm.
    """
    v = G.resample(points, spacing, closed=closed)
    r = G.resample(contour, spacing, closed=closed)
    d = np.linalg.norm(v - G.ClosestPoints(r, closed=closed)(v), axis=1)
    back = np.linalg.norm(r - G.ClosestPoints(v, closed=closed)(r), axis=1)
    return DistanceStats(float(d.mean()), float(np.percentile(d, 95)), float(d.max()),
                         float(max(d.max(), back.max())), len(v))


def dice(a, b) -> float:
    """Dice coefficient of two shapely regions: :math:`2|A \\cap B| / (|A| + |B|)`."""
    s = a.area + b.area
    return float(2.0 * a.intersection(b).area / s) if s > 0 else float("nan")


def _union(contours: list[np.ndarray]):
    from shapely.ops import unary_union

    return unary_union([G.polygon(c) for c in contours])


def _breast_regions(real: np.ndarray, virtual: np.ndarray):
    """Breast regions closed by their chest-wall chords, clipped to the common anterior part
    ``x >= max(min x_real, min x_virtual)`` so a different posterior cut does not count."""
    from shapely.geometry import box

    pr, pv = G.polygon(real), G.polygon(virtual)
    x0 = max(pr.bounds[0], pv.bounds[0])
    big = 1e6
    clip = box(x0, -big, big, big)
    return pr.intersection(clip), pv.intersection(clip)


def compression_degree(thickness_before_mm: float, thickness_after_mm: float) -> float:
    """Compression degree :math:`D = 1 - t_c / t_0` (-): the relative reduction of the mean
    breast thickness between the plates (Lapuebla-Ferri et al.)."""
    if thickness_before_mm <= 0:
        raise ValueError(f"thickness_before_mm = {thickness_before_mm} must be > 0")
    return 1.0 - thickness_after_mm / thickness_before_mm


def compute_metrics(alignment: Alignment, real: MammogramView, virtual: MammogramView, *,
                    D: float | None = None) -> Metrics:
    """Metrics of an alignment.

    * :math:`BS_{Av}` (eq. 4), :math:`TS_{Av}` (eq. 5): :func:`similarity_percent` of the
      breast and tumour objectives at the common angle :math:`\\theta_p` (the rotation
      applied to the view); ``bs_av_b`` and ``ts_av_t`` are the same at each contour's own
      optimum :math:`\\theta_{p,b}`, :math:`\\theta_{p,t}`.
    * :math:`\\theta_{p,b}`, :math:`\\theta_{p,t}`, :math:`\\theta_p = (\\theta_{p,b} +
      \\theta_{p,t})/2` (deg): from the golden-section searches.
    * ``D`` (-): compression degree of the simulation, passed through
      (:func:`compression_degree`).
    * :math:`d_T = \\lVert c(T_r) - c(T_v) \\rVert`, :math:`d_B = \\lVert c(B_r) - c(B_v)
      \\rVert` (mm): distances between the area centroids ``c`` of the real and aligned
      virtual tumour regions (the union of the paired tumour polygons: each outline
      paired with at most one on the other side, :func:`.geometry.pair_outlines`) and
      breast regions (open contour closed by its chest-wall chord).  ``d_T`` and the tumour Dice are computed
      whenever both views have tumour contours, also when the registration did not use
      them; :math:`TS_{Av}` only when it did (NaN otherwise).
    * Distance statistics (mm): :func:`distance_stats` of the aligned virtual contours.
    * Dice (-): :func:`dice` of the breast regions (clipped to the common anterior part,
      see ``_breast_regions``) and of the tumour regions.
    """
    from regtrack.errors import RegistrationError

    if virtual.view.upper() != alignment.view.upper() or real.view.upper() != alignment.view.upper():
        raise RegistrationError(f"metrics: alignment of the {alignment.view} view cannot be scored "
                                f"with real {real.view} / virtual {virtual.view} views")
    spacing = alignment.config.resample_mm
    rb, vb = _breast_regions(real.breast_contour, alignment.breast_contour)
    cb_r, cb_v = G.polygon(real.breast_contour).centroid, G.polygon(alignment.breast_contour).centroid
    d_B = float(math.hypot(cb_r.x - cb_v.x, cb_r.y - cb_v.y))
    bstats = distance_stats(alignment.breast_contour, real.breast_contour, closed=False,
                            spacing=spacing)
    ts_av = ts_av_t = d_T = dice_t = float("nan")
    tstats = None
    if alignment.tumour_objective is not None:
        ts_av = similarity_percent(alignment.tumour_objective, alignment.theta_p)
        ts_av_t = similarity_percent(alignment.tumour_objective, alignment.theta_p_t)
    real_t, virt_t = list(real.tumour_contours), list(alignment.tumour_contours or [])
    # also on a breast-only registration (outlines given, use_tumour = false): then d_T is
    # the error of a prediction that did not see the tumour, its outlines paired at theta_p
    pairs = alignment.tumour_pairs or G.pair_outlines(virt_t, real_t)
    if pairs:
        tr, tv = _union([real_t[k] for _, k in pairs]), _union([virt_t[j] for j, _ in pairs])
        d_T = float(math.hypot(tr.centroid.x - tv.centroid.x, tr.centroid.y - tv.centroid.y))
        dice_t = dice(tr, tv)
        if len(pairs) == 1:
            (j, k), = pairs
            tstats = distance_stats(virt_t[j], real_t[k], closed=True, spacing=spacing)
    return Metrics(
        view=alignment.view,
        bs_av=similarity_percent(alignment.breast_objective, alignment.theta_p),
        ts_av=ts_av, bs_av_b=similarity_percent(alignment.breast_objective, alignment.theta_p_b),
        ts_av_t=ts_av_t, theta_p_b=alignment.theta_p_b, theta_p_t=alignment.theta_p_t,
        theta_p=alignment.theta_p, D=D, d_T=d_T, d_B=d_B, breast_distance=bstats,
        tumour_distance=tstats, dice_breast=dice(rb, vb), dice_tumour=dice_t,
        evaluations_b=alignment.evaluations_b, evaluations_t=alignment.evaluations_t)
