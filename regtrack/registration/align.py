"""Rigid 2-D alignment of a virtual mammogram on a real one (Lapuebla-Ferri et al.).

1. *Nipple superposition*: the virtual view is translated so that its nipple ``n_v``
   falls on the real nipple ``n_p``.  A nipple the mammogram reader *detected* (the
   contour point farthest from the chest wall, :mod:`regtrack.imaging.mammogram.nipple`)
   is only an estimate: on a flat or turned front, or without a nipple in profile, the
   farthest point lies tens of millimetres along the skin from the nipple.  The reader
   says how flat the front is: ``u``, half the arc length of the run of skin points
   within 1 mm of the farthest distance, which it cannot tell apart.  Such an ``n_p`` is
   searched along the real skin line within ``W = NIPPLE_SEARCH_RUNS u`` of arc length
   either side (at most ``nipple_search_mm``), jointly with the rotation, as the most
   probable point given the outlines and the detection (a maximum a posteriori estimate;
   a grid of ``NIPPLE_GRID_MM``, then golden section):

   .. math::

       s^* = \\arg\\min_s \\; \\frac{h}{L_c} \\frac{F(s)}{2 \\sigma^2}
             + \\frac{s^2}{2 \\sigma_s^2}, \\qquad F(s) = \\min_\\theta F_b(\\theta; n_p(s)),

   ``s`` the arc length from the detected point (mm): the fit's residuals as ``K``
   samples ``h`` apart of which one per ``L_c`` (``RESIDUAL_CORRELATION_MM``) is
   independent, with the variance of the best fit, :math:`\\sigma^2 = \\max(F_{min} / K,
   \\sigma_0^2)` (:math:`\\sigma_0` = ``RESIDUAL_FLOOR_MM``; the same model as the
   tracking's rotation uncertainty, :mod:`regtrack.tracking.uncertainty`), and a prior
   centred on the detection, :math:`\\sigma_s = W / 2`.  Where the outlines decide the
   nipple the prior does not move it; where they cannot (a round front fits at any point)
   the detected point stays; a sharp apex (``u`` near 0) is kept as detected.  A nipple
   given by the user (``nipple_px``) is not moved.
2. *Rotation about the nipple*: a virtual point ``v`` maps to
   :math:`v(\\theta) = n_p + R(\\theta)(v - n_v)`.
3. *Closest-point objective*: both contours are resampled at equal arc length; for each
   virtual point the closest point ``r_c(i)`` of the real contour is found (KD-tree),

   .. math:: F_b(\\theta) = \\sum_i \\lVert v_i(\\theta) - r_{c(i)} \\rVert^2

   for the breast (open skin line) and :math:`F_t` likewise for the tumour contour(s).
   Virtual breast points matched to an end of the real skin line are left out of
   :math:`F_b` (``reject_ends_mm``, see :class:`Objective`).  With several tumours, each
   virtual outline is compared with one real outline only: the pairs of least total
   centroid distance once the virtual view is turned by :math:`\theta_{p,b}`
   (:func:`.geometry.pair_outlines`); a lesion of the model that the image does not show
   (outside the detector, or not outlined) is left out instead of being matched to
   another lesion's outline (warned).  Virtual tumour points off the real image are left
   out of :math:`F_t` (a lesion cut by the image edge is outlined only where it shows).
4. *Golden-section search* of :math:`F_b` and :math:`F_t` separately on
   :math:`[\\theta_0 - w, \\theta_0 + w]` (``w = bracket_deg``, default 30 deg; nominal
   :math:`\\theta_0 = 0` for both views because the MLO 45 deg pre-rotation is in the
   plate frame) gives :math:`\\theta_{p,b}` and :math:`\\theta_{p,t}`;
   :math:`\\theta_p = (\\theta_{p,b} + \\theta_{p,t}) / 2` is applied to the whole view.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from regtrack.errors import RegistrationError
from regtrack.registration import geometry as G
from regtrack.registration.config import RegistrationConfig
from regtrack.registration.golden import GoldenResult, golden_section
from regtrack.views import MammogramView

log = logging.getLogger(__name__)


@dataclass
class Objective:
    r"""Closest-point objective of one contour pair (virtual -> real), in mm.

    With ``ends`` (the two end points of an open real contour) and ``reject_mm > 0``, a
    virtual point whose closest real point lies within ``reject_mm`` of an end is left out
    (the boundary rule of ICP, Turk & Levoy 1994): the real skin line stops at the image
    edge or the pectoral line while the projected model may reach further, and those
    points, all matched to the end, would pull the rotation.  With ``extent`` (the real
    image's width and height, mm, canonical frame from its corner), a virtual point off
    the image is left out: a tumour cut by the image edge is outlined only where the
    image shows it.  With ``k`` of the ``K``
    points kept, :math:`F = (K / k) \sum_{kept} d_i^2`, which is the paper's plain sum
    when nothing is left out.  :meth:`distances` always returns all ``K`` points (the
    paper's metrics use them).
    """

    virtual: np.ndarray          # (K, 2) resampled virtual points, nipple-centred (v - n_v)
    closest: G.ClosestPoints     # on the resampled real contour
    nipple: np.ndarray           # real nipple n_p
    ends: np.ndarray | None = None   # (2, 2) end points of an open real contour
    reject_mm: float = 0.0
    extent: np.ndarray | None = None  # (width, height) mm of the real image: points off it are left out

    def points(self, theta_deg: float) -> np.ndarray:
        """Virtual points after superposition and rotation by ``theta_deg``."""
        return self.virtual @ G.rotation(theta_deg).T + self.nipple

    def _pairs(self, theta_deg: float) -> tuple[np.ndarray, np.ndarray]:
        p = self.points(theta_deg)
        c = self.closest(p)
        d = np.linalg.norm(p - c, axis=1)
        keep = np.ones(len(d), bool)
        if self.ends is not None and self.reject_mm > 0.0:
            keep &= np.linalg.norm(c[:, None, :] - self.ends[None], axis=2).min(axis=1) > self.reject_mm
        if self.extent is not None:
            keep &= (p >= 0.0).all(axis=1) & (p <= self.extent).all(axis=1)
        return d, keep

    def distances(self, theta_deg: float) -> np.ndarray:
        """Per-point closest distances (mm) at ``theta_deg`` (every point)."""
        return self._pairs(theta_deg)[0]

    def kept(self, theta_deg: float) -> np.ndarray:
        """(K,) bool: the points that enter F at ``theta_deg``."""
        return self._pairs(theta_deg)[1]

    def __call__(self, theta_deg: float) -> float:
        """F(theta): sum of squared closest distances (mm^2), scaled as above."""
        d, keep = self._pairs(theta_deg)
        k = int(keep.sum())
        if k == 0:  # every point beyond the real contour's ends: no information
            return float(np.sum(d**2))
        return float(np.sum(d[keep] ** 2) * len(d) / k)


@dataclass
class Alignment:
    """Result of :func:`align` (angles in degrees, lengths in mm).

    Attributes
    ----------
    view : str
    theta_p_b, theta_p_t, theta_p : float
        Optimal rotation for the breast, for the tumour, and their mean (deg).
        ``theta_p_t`` is NaN when the tumour is not used.
    translation : (2,) float
        ``n_p - n_v``: nipple superposition (mm).
    nipple : (2,) float
        Real nipple ``n_p`` (mm), the centre of rotation.
    detected_nipple, nipple_slide_mm :
        The reader's detected nipple (mm) and the arc length (mm, signed along the skin
        line) from it to ``nipple`` when the registration searched it (None, 0 when the
        nipple was given or not searched).
    tumour_pairs : list of (int, int)
        ``(j, k)``: virtual tumour outline ``j`` compared with real outline ``k`` in
        :math:`F_t` (empty when the tumour is not used).
    F_b, F_t : dict
        Objective values (mm^2) at ``theta = 0``, at its own optimum and at ``theta_p``.
    evaluations_b, evaluations_t : int
        Golden-section (+ coarse scan) function evaluations.
    bracket_deg : (2,) float
        Search interval (deg).
    breast_contour, tumour_contours :
        The virtual contours superposed and rotated by ``theta_p`` (mm, real frame).
    breast_objective, tumour_objective : Objective
        For re-evaluation by the metrics.
    config : RegistrationConfig
    warnings : list of str
    """

    view: str
    theta_p_b: float
    theta_p_t: float
    theta_p: float
    translation: np.ndarray
    nipple: np.ndarray
    virtual_nipple: np.ndarray
    F_b: dict
    F_t: dict
    evaluations_b: int
    evaluations_t: int
    bracket_deg: tuple[float, float]
    breast_contour: np.ndarray
    tumour_contours: list[np.ndarray]
    breast_objective: Objective
    tumour_objective: Objective | None
    config: RegistrationConfig
    warnings: list[str] = field(default_factory=list)
    detected_nipple: np.ndarray | None = None
    nipple_slide_mm: float = 0.0
    tumour_pairs: list[tuple[int, int]] = field(default_factory=list)

    def transform(self, xy, theta_deg: float | None = None) -> np.ndarray:
        """Map virtual points (mm) into the real frame: ``n_p + R(theta)(v - n_v)``
        (default ``theta = theta_p``)."""
        th = self.theta_p if theta_deg is None else theta_deg
        return (np.asarray(xy, float) - self.virtual_nipple) @ G.rotation(th).T + self.nipple

    def to_dict(self) -> dict:
        """JSON-ready summary (angles in deg, contours in mm)."""
        return {
            "view": self.view, "theta_p_b_deg": self.theta_p_b,
            "theta_p_t_deg": None if np.isnan(self.theta_p_t) else self.theta_p_t,
            "theta_p_deg": self.theta_p, "translation_mm": self.translation.tolist(),
            "nipple_mm": self.nipple.tolist(),
            "nipple_detected_mm": (None if self.detected_nipple is None
                                   else self.detected_nipple.tolist()),
            "nipple_slide_mm": self.nipple_slide_mm,
            "F_b_mm2": self.F_b, "F_t_mm2": self.F_t,
            "evaluations_b": self.evaluations_b, "evaluations_t": self.evaluations_t,
            "tumour_pairs": [list(p) for p in self.tumour_pairs],
            "bracket_deg": list(self.bracket_deg),
            "breast_contour_mm": self.breast_contour.tolist(),
            "tumour_contours_mm": [c.tolist() for c in self.tumour_contours],
            "warnings": self.warnings,
        }


#: coordinates beyond this (mm) are a unit or spacing error, not a breast (and would
#: overflow the squared distances of the objective)
MAX_COORD_MM = 1e5


def _label(v: MammogramView, who: str) -> str:
    src = f" ({v.source})" if v.source else ""
    return f"{who} {v.view} view{src}"


def _closed_at_chest_wall(bc: np.ndarray):
    """The region of a skin contour (canonical mm, x from the chest-wall edge towards the
    nipple) closed by carrying its two ends horizontally to the chest-wall edge."""
    x0 = min(0.0, float(bc[:, 0].min()))
    return G.polygon(np.vstack([bc, [[x0, bc[-1, 1]], [x0, bc[0, 1]]]]))


def check_view(v: MammogramView, who: str, cfg: RegistrationConfig) -> None:
    """Raise :class:`RegistrationError` on degenerate inputs (one line naming the view)."""
    name = _label(v, who)
    bc = np.asarray(v.breast_contour, float)
    if bc.ndim != 2 or bc.shape[1] != 2 or len(bc) < cfg.min_breast_points:
        raise RegistrationError(
            f"{name}: breast contour has {len(bc)} points (< {cfg.min_breast_points}); "
            "check the mammogram segmentation or the simulation result")
    nip = np.asarray(v.nipple, float).reshape(-1)
    if not (np.isfinite(bc).all() and nip.shape == (2,) and np.isfinite(nip).all()):
        raise RegistrationError(f"{name}: breast contour or nipple is not finite; give the "
                                "nipple explicitly (case.toml [views.*] nipple_px)")
    if max(np.abs(bc).max(), np.abs(nip).max()) > MAX_COORD_MM:
        raise RegistrationError(f"{name}: breast contour or nipple lies more than "
                                f"{MAX_COORD_MM:g} mm from the origin; check the pixel spacing")
    breast = G.polygon(bc)
    if breast.is_empty or breast.area <= 0.0:
        raise RegistrationError(f"{name}: breast contour encloses no area (collinear or "
                                "coincident points); check the segmentation or the simulation")
    if not cfg.use_tumour:
        return
    if not v.tumour_contours:
        fix = ("annotate it (case.toml [views.*] tumour_polygon or tumour_mask)"
               if who == "real" else "the model has no tumour region")
        raise RegistrationError(f"{name}: no tumour contour; {fix}, or set [registration] "
                                "use_tumour = false to align on the breast contour only")
    for k, t in enumerate(v.tumour_contours):
        t = np.asarray(t, float)
        if t.ndim != 2 or t.shape[1:] != (2,) or len(t) < cfg.min_tumour_points or not np.isfinite(t).all():
            raise RegistrationError(
                f"{name}: tumour contour {k} has {len(t)} points (< {cfg.min_tumour_points}) "
                "or non-finite values; redraw the tumour polygon")
        tp = G.polygon(t)
        if tp.is_empty or tp.area <= 0.0 or np.abs(t).max() > MAX_COORD_MM:
            raise RegistrationError(f"{name}: tumour contour {k} encloses no area or lies more "
                                    f"than {MAX_COORD_MM:g} mm away; redraw the tumour polygon")
        # an annotation check (the model's own tumour lies inside its silhouette by
        # construction): against the skin line closed along the chest-wall edge x = 0 of
        # the image, since its ends may stop short of that edge and a chord would cut off
        # a tumour at the chest wall
        c = tp.representative_point()
        if who == "real" and not _closed_at_chest_wall(bc).covers(c):
            raise RegistrationError(
                f"{name}: tumour contour {k} (near x={c.x:.1f}, y={c.y:.1f} mm) lies outside the "
                "breast contour; check the tumour annotation's pixel grid and the view's flip")


def _breast_objective(virtual: np.ndarray, real: np.ndarray, *, nv: np.ndarray, npr: np.ndarray,
                      cfg: RegistrationConfig) -> Objective:
    r = G.resample(real, cfg.resample_mm, closed=False)
    v = G.resample(virtual, cfg.resample_mm, closed=False)
    cp = G.ClosestPoints(r, closed=False, segment=cfg.match == "segment")
    return Objective(v - nv, cp, npr, ends=r[[0, -1]], reject_mm=cfg.reject_ends_mm)


def _tumour_objective(virtual: list[np.ndarray], real: list[np.ndarray],
                      pairs: list[tuple[int, int]], *, nv: np.ndarray, npr: np.ndarray,
                      cfg: RegistrationConfig, extent: np.ndarray | None = None) -> Objective:
    """F_t over the paired outlines: each virtual outline's points matched on its own real
    outline only (:func:`.geometry.pair_outlines`), those off the real image left out."""
    vs, parts, n = [], [], 0
    for j, k in pairs:
        v = G.resample(virtual[j], cfg.resample_mm, closed=True)
        r = G.resample(real[k], cfg.resample_mm, closed=True)
        parts.append((slice(n, n + len(v)),
                      G.ClosestPoints(r, closed=True, segment=cfg.match == "segment")))
        vs.append(v)
        n += len(v)
    cp = parts[0][1] if len(parts) == 1 else G.PairedClosestPoints(parts)
    return Objective(np.vstack(vs) - nv, cp, npr, extent=extent)


def image_extent(v: MammogramView) -> np.ndarray | None:
    """(width, height) mm of a real view's image in the canonical frame (x from the
    chest-wall edge, y down, from the image's corner), from the reader's pixel grid; None
    when the view does not say (a view not read from an image)."""
    from regtrack.imaging.mammogram.orient import Orientation

    im = (v.meta or {}).get("image") or {}
    o, sp = im.get("orientation"), im.get("spacing_mm")
    if not o or sp is None:
        return None
    rows, cols = Orientation(tuple(o["source_shape"][:2]), bool(o.get("transpose"))).shape
    return np.array([cols * float(sp[1]), rows * float(sp[0])])


def _search(obj: Objective, lo: float, hi: float, cfg: RegistrationConfig) -> GoldenResult:
    n0 = 0
    if cfg.coarse_step_deg > 0:
        grid = np.arange(lo, hi + 1e-9, cfg.coarse_step_deg)
        vals = [obj(t) for t in grid]
        n0 = len(grid)
        k = int(np.argmin(vals))
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    r = golden_section(obj, lo, hi, tol=cfg.tol_deg)
    return GoldenResult(r.x, r.fun, r.evaluations + n0, r.bracket, r.at_edge)


#: Grid step (mm of skin line) of the nipple search before its golden-section refinement.
NIPPLE_GRID_MM = 5.0
#: The nipple search's half-window in runs ``u`` of the detected nipple (module docstring).
NIPPLE_SEARCH_RUNS = 3.0
#: Correlation length (mm) of the contour residuals and the floor (mm) of their spread in
#: the nipple search: one independent residual per 10 mm of contour, none resolved below
#: the 0.5 mm resampling (the tracking's defaults, regtrack.tracking.config).
RESIDUAL_CORRELATION_MM = 10.0
RESIDUAL_FLOOR_MM = 0.5


def nipple_run(real) -> float:
    """``u`` (mm) of the nipple on the real view: half the arc length over which the reader
    detected it (0 when given, or when the view does not say)."""
    info = (getattr(real, "meta", None) or {}).get("nipple") or {}
    if not str(info.get("method", "")).startswith("detected"):
        return 0.0
    return float(info.get("tangential_uncertainty_mm") or 0.0)


def nipple_window(v: MammogramView, cfg: RegistrationConfig) -> float:
    """Half-window (mm of skin line) of the nipple search on the real view ``v``:
    ``NIPPLE_SEARCH_RUNS`` times the reader's run ``u`` (0 for a nipple given by the
    user), at most ``cfg.nipple_search_mm``."""
    return min(NIPPLE_SEARCH_RUNS * nipple_run(v), cfg.nipple_search_mm)


def _nipple_on_skin(ob: Objective, contour: np.ndarray, window: float, lo: float, hi: float,
                    cfg: RegistrationConfig) -> tuple[np.ndarray, float, bool]:
    """The real nipple on the open skin line ``contour`` within ``window`` mm of arc length
    of ``ob.nipple``, the most probable given the outlines (module docstring), its signed
    arc length (mm) from ``ob.nipple``, and whether it lies at an end of the searched
    stretch (the best fit may lie beyond it)."""
    c = G.resample(np.asarray(contour, float), cfg.resample_mm, closed=False)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    s0 = float(s[int(np.argmin(np.linalg.norm(c - ob.nipple, axis=1)))])
    a, b = max(0.0, s0 - window), min(float(s[-1]), s0 + window)

    def at(x: float) -> np.ndarray:
        return np.array([np.interp(x, s, c[:, 0]), np.interp(x, s, c[:, 1])])

    coarse = replace(cfg, tol_deg=max(cfg.tol_deg, 0.01))

    def best(x: float) -> float:
        return _search(replace(ob, nipple=at(x)), lo, hi, coarse).fun

    grid = np.linspace(a, b, max(int(np.ceil((b - a) / NIPPLE_GRID_MM)), 1) + 1)
    fit = np.array([best(x) for x in grid])
    var = max(float(fit.min()) / max(len(ob.virtual), 1), RESIDUAL_FLOOR_MM ** 2)
    weight = cfg.resample_mm / RESIDUAL_CORRELATION_MM / (2.0 * var)
    prior = 2.0 * (0.5 * window) ** 2

    def posterior(x: float, f: float | None = None) -> float:
        return weight * (best(x) if f is None else f) + (x - s0) ** 2 / prior

    vals = [posterior(x, f) for x, f in zip(grid, fit)]
    k = int(np.argmin(vals))
    x = float(grid[k])
    if len(grid) > 2:
        r = golden_section(posterior, float(grid[max(k - 1, 0)]),
                           float(grid[min(k + 1, len(grid) - 1)]), tol=0.1)
        if r.fun < vals[k]:
            x = r.x
    return at(x), x - s0, min(x - a, b - x) < 0.2  # the golden section's 0.1 mm, twice


def breast_rotation(alignment: Alignment, nipple) -> float:
    """:math:`\\theta_{p,b}` (deg) of ``alignment``'s breast objective searched again with the
    real nipple at ``nipple`` (mm) instead of :math:`n_p`, over the same bracket: how the
    registration answers a different nipple on the real image."""
    ob = replace(alignment.breast_objective, nipple=np.asarray(nipple, float))
    lo, hi = alignment.bracket_deg
    return _search(ob, lo, hi, alignment.config).x


def align(real: MammogramView, virtual: MammogramView, *,
          config: RegistrationConfig | None = None) -> Alignment:
    """Align ``virtual`` on ``real``: nipple superposition + golden-section rotation.

    Parameters
    ----------
    real, virtual : MammogramView
        Same view and laterality, canonical 2-D frame (mm).
    config : RegistrationConfig, optional

    Returns
    -------
    Alignment

    Raises
    ------
    RegistrationError
        Different views/sides, too few contour points, missing tumour contour, tumour
        outside the breast, non-finite input.
    """
    cfg = config or RegistrationConfig()
    if real.view.upper() != virtual.view.upper():
        raise RegistrationError(f"cannot align a virtual {virtual.view} view on a real "
                                f"{real.view} view; project the matching view")
    if real.laterality != virtual.laterality:
        raise RegistrationError(f"real {real.view} view is side {real.laterality} but the "
                                f"model is side {virtual.laterality}; check case.toml [mri] side")
    check_view(real, "real", cfg)
    check_view(virtual, "virtual", cfg)
    npr = np.asarray(real.nipple, float)
    nv = np.asarray(virtual.nipple, float)
    th0 = cfg.nominal_deg(real.view)
    lo, hi = th0 - cfg.bracket_deg, th0 + cfg.bracket_deg
    warnings: list[str] = []

    ob = _breast_objective(virtual.breast_contour, real.breast_contour, nv=nv, npr=npr, cfg=cfg)
    detected, slide = None, 0.0
    window = nipple_window(real, cfg)
    if window >= cfg.resample_mm:
        detected = npr
        npr, slide, at_end = _nipple_on_skin(ob, real.breast_contour, window, lo, hi, cfg)
        ob = replace(ob, nipple=npr)
        log.info("%s: nipple placed %.1f mm along the skin line from the detected one",
                 real.view, slide)
        if at_end:
            warnings.append(f"the nipple search stopped at the end of the skin line or of "
                            f"its {window:.0f} mm window ({slide:+.1f} mm from the detected "
                            f"nipple); check the outline, or mark the nipple "
                            f"([views.{real.view}] nipple_px)")
    rb = _search(ob, lo, hi, cfg)
    if rb.at_edge:
        warnings.append(f"theta_p,b = {rb.x:.2f} deg is at the edge of the search bracket "
                        f"[{lo:g}, {hi:g}]; widen [registration] bracket_deg")
    ot, rt, pairs = None, None, []
    if cfg.use_tumour:
        vt, rtc = list(virtual.tumour_contours), list(real.tumour_contours)
        pairs = G.pair_outlines([(np.asarray(c, float) - nv) @ G.rotation(rb.x).T + npr for c in vt],
                                rtc)
        for j in sorted(set(range(len(vt))) - {j for j, _ in pairs}):
            warnings.append(f"virtual tumour {j + 1} has no outline on the real view (outside the "
                            "image, or not outlined): left out of theta_p,t")
        for k in sorted(set(range(len(rtc))) - {k for _, k in pairs}):
            warnings.append(f"tumour outline {k + 1} of the real view has no tumour in the model "
                            "near it: left out of theta_p,t")
        ot = _tumour_objective(vt, rtc, pairs, nv=nv, npr=npr, cfg=cfg, extent=image_extent(real))
        rt = _search(ot, lo, hi, cfg)
        if rt.at_edge:
            warnings.append(f"theta_p,t = {rt.x:.2f} deg is at the edge of the search bracket "
                            f"[{lo:g}, {hi:g}]; widen [registration] bracket_deg")
    theta_t = rt.x if rt is not None else float("nan")
    theta_p = 0.5 * (rb.x + rt.x) if rt is not None else rb.x
    for w in warnings:
        log.warning("%s: %s", _label(virtual, "virtual"), w)

    def rot(xy):
        return (np.asarray(xy, float) - nv) @ G.rotation(theta_p).T + npr

    F_b = {"theta_0": ob(0.0), "theta_p_b": rb.fun, "theta_p": ob(theta_p)}
    F_t = {} if ot is None else {"theta_0": ot(0.0), "theta_p_t": rt.fun, "theta_p": ot(theta_p)}
    log.info("%s: theta_p,b = %.3f deg (%d evaluations), theta_p,t = %.3f deg, theta_p = %.3f deg",
             real.view, rb.x, rb.evaluations, theta_t, theta_p)
    return Alignment(
        view=real.view, theta_p_b=rb.x, theta_p_t=theta_t, theta_p=theta_p,
        translation=npr - nv, nipple=npr, virtual_nipple=nv, F_b=F_b, F_t=F_t,
        evaluations_b=rb.evaluations, evaluations_t=0 if rt is None else rt.evaluations,
        bracket_deg=(lo, hi), breast_contour=rot(virtual.breast_contour),
        tumour_contours=[rot(t) for t in virtual.tumour_contours],
        breast_objective=ob, tumour_objective=ot, config=cfg, warnings=warnings,
        detected_nipple=detected, nipple_slide_mm=float(slide), tumour_pairs=pairs)
