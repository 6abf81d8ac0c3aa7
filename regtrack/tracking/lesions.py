"""The MRI lesion(s) predicted on each real mammogram: what ``regtrack run`` reports.

Tracking mode (no tumour outline on the mammograms) and paper mode (outlines given) both
make this prediction from a registration on the **breast outline and nipple only**
(:math:`\\theta_p = \\theta_{p,b}`, :func:`breast_alignment`), so that it never uses the
answer: in paper mode the distance to the annotated outline (``error_mm``) is then an
honest measure of the tracking error, beside the paper's :math:`d_T` (which aligns on the
tumour too).

Per lesion (each tumour of the model, :func:`predict_lesions`):

* the centroid: the lesion's mass centroid carried by the finite-element deformation
  (:func:`regtrack.tracking.mri_to_view.track_tumour`), projected and registered;
* the outline: the projected outline of its deformed tetrahedra, registered;
* a 1-sigma radius :math:`\\sigma` (mm), :func:`lesion_sigma`, from four independent terms
  in quadrature:

  .. math::

      \\sigma^2 = \\max(\\sigma_{res}, \\sigma_{min})^2 + (r\\,\\sigma_\\theta)^2
                 + \\sigma_{model}^2 + \\sigma_{nip}^2

  - :math:`\\sigma_{res}`: the locally weighted RMS breast residual around the point
    (:func:`regtrack.tracking.uncertainty.residual_sigma`);
  - :math:`r\\,\\sigma_\\theta`: the registration's angular uncertainty
    (:func:`angular_sigma`) times the distance ``r`` (mm) of the point from the nipple,
    the centre of rotation;
  - :math:`\\sigma_{model} = |\\Delta| \\sqrt{(\\sigma_D / D)^2 + \\alpha^2}`: the
    sensitivity of the prediction to the model.  :math:`\\Delta` is the in-plane
    displacement (mm) of the lesion relative to the nipple caused by the compression (its
    projected position, relative to the projected nipple, after minus before).  To first
    order it scales with the compression degree ``D``, so an uncertainty
    :math:`\\sigma_D` of ``D`` moves the lesion by :math:`|\\Delta| \\sigma_D / D`
    (``sigma_D`` from the thickness's source: the DICOM's BodyPartThickness with
    ``thickness_sigma_mm``, or the protocol's nominal ``D`` with ``degree_sigma``).
    :math:`\\alpha` (``material_rel``) is the relative sensitivity of the prediction to
    the tissue's :math:`c_1` and :math:`\\nu` (with the plates driven to a gap, a
    homogeneous neo-Hookean breast deforms nearly independently of :math:`c_1`; gravity
    and :math:`\\nu` change the lateral spread).  No extra simulation is run per case: the
    default 0.16 is the median that re-simulation measured on the Pelicano exams of
    docs/truth-cases.md (``pipelines/bench_accuracy.py --variants track_c1,track_nu``:
    c1 times 1.3 and nu - 0.02, the 1-sigma of ``[tracking]``, moved the predicted
    centroid by 0.5 to 2.4 mm in quadrature, 0.08 to 0.39 of :math:`|\\Delta|` over seven
    lesions of six exams);
  - :math:`\\sigma_{nip} = u / \\sqrt{3}`: where the nipple was detected on the
    mammogram.  The detector takes the middle of the run of contour points within
    ``nipple_delta_mm`` of the farthest from the chest wall (:mod:`regtrack.imaging.
    mammogram.nipple`); on a flat compressed apex that run is long, any of its points
    could be the nipple, and the registration carries the whole prediction with it.  With
    ``u`` half the run's arc length (mm), a position uniform over the run has the standard
    deviation ``u / sqrt(3)``.  Zero when the nipple is given (``nipple_px``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.uncertainty import Residual, residual_sigma

log = logging.getLogger(__name__)


@dataclass
class LesionPrediction:
    """One MRI lesion predicted on one real mammogram (mm of the real canonical frame).

    ``centroid_px`` is the (row, col) of the DICOM's own grid; ``terms_mm`` the four
    uncertainty terms of :func:`lesion_sigma`; ``error_mm`` the distance from the predicted
    centroid to the area centroid of the annotated outline (paper mode; None in tracking
    mode), ``annotated_mm`` that centroid; ``mri_lps_mm`` the lesion's volume centroid in
    the MRI (DICOM patient frame, LPS mm); ``nipple_mm`` / ``nipple_px`` the nipple on the
    mammogram, the centre of the registration's rotation.
    """

    view: str
    lesion: int
    centroid_mm: np.ndarray
    centroid_px: np.ndarray | None
    outline_mm: np.ndarray | None
    sigma_mm: float
    terms_mm: dict
    theta_deg: float
    theta_sigma_deg: float
    distance_from_nipple_mm: float
    inplane_shift_mm: float
    error_mm: float | None = None
    annotated_mm: np.ndarray | None = None
    outline_px: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    mri_lps_mm: np.ndarray | None = None
    nipple_mm: np.ndarray | None = None
    nipple_px: np.ndarray | None = None

    def to_dict(self) -> dict:
        def arr(a):
            return None if a is None else np.asarray(a, float).tolist()
        return {"view": self.view, "lesion": self.lesion, "centroid_mm": arr(self.centroid_mm),
                "centroid_px_rc": arr(self.centroid_px), "sigma_mm": self.sigma_mm,
                "uncertainty_terms_mm": self.terms_mm, "theta_p_b_deg": self.theta_deg,
                "theta_sigma_deg": self.theta_sigma_deg,
                "distance_from_nipple_mm": self.distance_from_nipple_mm,
                "inplane_shift_mm": self.inplane_shift_mm, "error_mm": self.error_mm,
                "annotated_centroid_mm": arr(self.annotated_mm),
                "outline_mm": arr(self.outline_mm), "outline_px_rc": arr(self.outline_px),
                "mri_lps_mm": arr(self.mri_lps_mm), "nipple_mm": arr(self.nipple_mm),
                "nipple_px_rc": arr(self.nipple_px), "notes": self.notes}


def breast_alignment(alignment, real, virtual):
    """The registration on the breast outline and nipple only (``use_tumour = false``):
    ``alignment`` itself when it already is one, else a new golden-section search."""
    from regtrack.registration import align

    if alignment.tumour_objective is None:
        return alignment
    cfg = dataclasses.replace(alignment.config, use_tumour=False)
    return align(real, virtual, config=cfg)


def angular_sigma(objective, theta_deg: float, *, correlation_mm: float, spacing_mm: float,
                  step_deg: float = 0.5, cap_deg: float = 10.0) -> float:
    r"""1-sigma uncertainty (deg) of the breast rotation :math:`\theta_{p,b}`.

    Least squares on the ``K`` closest-point distances :math:`d_i(\theta)` (Gauss-Newton,
    :math:`F'' \approx 2 \sum_i J_i^2`):

    .. math::

        \sigma_\theta^2 = \frac{2 s^2}{F''(\theta)} \cdot \frac{L_c}{h},
        \qquad s^2 = \frac{F(\theta)}{K - 1}

    with ``F''`` by central differences (``step_deg``).  The contour is resampled every
    ``h`` = ``spacing_mm``; neighbouring residuals are not independent, so the variance is
    inflated by the number of samples per correlation length ``L_c`` = ``correlation_mm``
    (the effective number of independent residuals is the contour length over ``L_c``).
    A flat or concave objective gives ``cap_deg``.
    """
    k = max(len(objective.virtual), 2)
    f0 = objective(theta_deg)
    fp, fm = objective(theta_deg + step_deg), objective(theta_deg - step_deg)
    curv = (fp - 2.0 * f0 + fm) / step_deg ** 2  # mm^2 / deg^2
    if not (math.isfinite(curv) and curv > 0.0):
        return float(cap_deg)
    s2 = f0 / (k - 1)
    var = 2.0 * s2 / curv * max(1.0, correlation_mm / spacing_mm)
    return float(min(math.sqrt(var), cap_deg))


def lesion_sigma(*, residual_mm: float, r_mm: float, theta_sigma_deg: float,
                 shift_mm: float, D: float | None, sigma_D: float, nipple_run_mm: float = 0.0,
                 config: TrackingConfig) -> tuple[float, dict]:
    """1-sigma radius (mm) and its terms (module docstring); ``nipple_run_mm`` is ``u``."""
    rot = r_mm * math.radians(theta_sigma_deg)
    rel_D = sigma_D / D if D else 0.0
    model = abs(shift_mm) * math.hypot(rel_D, config.material_rel)
    res = max(residual_mm, config.min_residual_mm)
    nip = nipple_run_mm / math.sqrt(3.0)
    sigma = math.sqrt(res ** 2 + rot ** 2 + model ** 2 + nip ** 2)
    return sigma, {"registration_residual": float(residual_mm), "rotation": float(rot),
                   "model": float(model), "nipple": float(nip)}


def nipple_run(real) -> float:
    """``u`` (mm) of the nipple on the real view: half the arc length over which the
    detector found it (0 when given, or when the view does not say)."""
    info = (getattr(real, "meta", None) or {}).get("nipple") or {}
    return float(info.get("tangential_uncertainty_mm") or 0.0)


def _area_centroid(contours) -> np.ndarray | None:
    from shapely.ops import unary_union

    from regtrack.registration.geometry import polygon

    if not contours:
        return None
    u = unary_union([polygon(np.asarray(c, float)) for c in contours])
    if u.is_empty or u.area <= 0:
        return None
    return np.array([u.centroid.x, u.centroid.y])


def _inplane_shift(model, positions, frame, tets, weights) -> float:
    """|in-plane displacement| (mm) of a region's centroid relative to the nipple."""
    def proj(p):
        return frame.to_local(np.atleast_2d(p))[:, :2]

    ref = weights @ model.points[tets].mean(axis=1)
    cur = weights @ positions[tets].mean(axis=1)
    n0, n1 = model.points[model.nipple], positions[model.nipple]
    d = (proj(cur) - proj(n1)) - (proj(ref) - proj(n0))
    return float(np.linalg.norm(d))


def predict_lesions(model, *, view: str, positions, virtual, real, alignment, D: float | None,
                    sigma_D: float, config: TrackingConfig | None = None) -> list[LesionPrediction]:
    """Every tumour of ``model`` predicted on the ``real`` mammogram of ``view``.

    Parameters
    ----------
    model : BreastModel
        Reference (prone MRI) mesh with its tumour region(s).
    positions : (N, 3) float
        Deformed node positions of the view's simulation (mm).
    virtual : VirtualMammogram
        Its projection (plate frame and point source).
    real : MammogramView
        The real view (pixel frame; annotated outlines, if any, for ``error_mm``).
    alignment : Alignment
        A breast-only registration (:func:`breast_alignment`).
    D, sigma_D : float
        Compression degree of the simulation and its 1-sigma uncertainty (-).
    """
    from regtrack.model.types import TUMOUR
    from regtrack.tracking.mri_to_view import region_outline
    from regtrack.tracking.viewmap import InPlane, PixelFrame, ViewMap

    cfg = config or TrackingConfig()
    sel = model.region == TUMOUR
    if not sel.any():
        return []
    ids = np.where(model.tumour_id > 0, model.tumour_id, 1)
    ob = alignment.breast_objective
    th = float(alignment.theta_p)
    sig_th = angular_sigma(ob, th, correlation_mm=cfg.correlation_mm,
                           spacing_mm=alignment.config.resample_mm)
    vm = ViewMap(view, np.asarray(positions, float), virtual.frame,
                 InPlane.from_alignment(alignment), PixelFrame.from_view(real), virtual.source,
                 Residual(ob.points(th), ob.distances(th)), real)
    annotated = _area_centroid(real.tumour_contours)
    nip, u_nip = vm.inplane.nipple, nipple_run(real)
    nip_px = None if vm.pixels is None else vm.pixels.mm_to_px(nip)
    vol = np.abs(model.tet_volumes())
    out = []
    for k in np.unique(ids[sel]):
        m = sel & (ids == k)
        tets = model.tets[m]
        w = vol[m] / vol[m].sum()
        x = w @ vm.positions[tets].mean(axis=1)
        xy = vm.to_real(x[None])[0]
        outline = region_outline(vm, tets)
        r = float(np.linalg.norm(xy - vm.inplane.nipple))
        res = float(residual_sigma(xy[None], vm.residual, scale_mm=cfg.residual_scale_mm)[0])
        shift = _inplane_shift(model, vm.positions, virtual.frame, tets, w)
        sigma, terms = lesion_sigma(residual_mm=res, r_mm=r, theta_sigma_deg=sig_th,
                                    shift_mm=shift, D=D, sigma_D=sigma_D,
                                    nipple_run_mm=u_nip, config=cfg)
        px = None if vm.pixels is None else vm.pixels.mm_to_px(xy)
        opx = None if (vm.pixels is None or outline is None) else vm.pixels.mm_to_px(outline)
        err = None if annotated is None else float(np.linalg.norm(xy - annotated))
        lps = model.frame.to_patient((w @ model.points[tets].mean(axis=1))[None])[0]
        out.append(LesionPrediction(view, int(k), xy, px, outline, sigma, terms, th, sig_th, r,
                                    shift, err, annotated, opx, mri_lps_mm=lps, nipple_mm=nip,
                                    nipple_px=nip_px))
    return out
