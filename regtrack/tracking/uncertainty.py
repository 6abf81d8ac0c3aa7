"""Uncertainty of a position predicted in a real mammogram (mm).

A predicted position ``p`` in a real mammogram (a lesion's centroid, an MRI point, a point
carried from the other view) has the 1-sigma radius (mm) of four independent terms in
quadrature (:func:`prediction_sigma`):

.. math::

    \\sigma^2 = \\max(\\sigma_{res}, \\sigma_{min})^2 + (r\\,\\sigma_\\theta)^2
               + \\sigma_{model}^2 + \\sigma_{nip}^2

- :math:`\\sigma_{res}`: the locally weighted RMS breast residual around the point
  (:func:`residual_sigma`);
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
- :math:`\\sigma_{nip}`: where the nipple was detected on the mammogram.  The detector
  takes the middle of the run of contour points within ``nipple_delta_mm`` of the
  farthest from the chest wall (:mod:`regtrack.imaging.mammogram.nipple`); on a flat
  compressed apex that run is long and any of its points could be the nipple.  With
  ``u`` half the run's arc length (mm), a position uniform over the run has the standard
  deviation :math:`h = u / \\sqrt{3}` along the run.  The registration does not carry a
  prediction rigidly with its nipple: it turns the outline to fit it again.  So the
  breast rotation is searched again with the real nipple at :math:`n_p \\pm h\\,t`
  (``t`` the run's direction), giving :math:`\\theta_\\pm`; a point predicted at ``p``
  moves to :math:`p_\\pm = n_p \\pm h t + R(\\theta_\\pm - \\theta_p)(p - n_p)`, and
  :math:`\\sigma_{nip}(p) = |p_+ - p_-| / 2`, the first-order propagation of ``h``
  through the registration (:class:`NippleMoves`).  A point at the nipple moves by ``h``;
  the centre of a circular outline hardly moves (the turn that re-fits the circle brings
  it back).  Zero when the nipple is given (``nipple_px``).

Every prediction comes from the registration on the breast outline and nipple only
(:func:`regtrack.tracking.viewmap.breast_alignment`; :math:`\\theta_p = \\theta_{p,b}`), so
``regtrack run`` (a lesion of the model) and ``regtrack track`` (an MRI point or region, a
point of the other view) give one position and one radius for the same place.

Not modelled: the error of the MRI annotation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from regtrack.registration.align import breast_rotation, nipple_run
from regtrack.registration.geometry import rotation


@dataclass
class Residual:
    """Aligned virtual contour samples (real frame, mm) and their closest distances (mm)."""

    points: np.ndarray     # (K, 2)
    distances: np.ndarray  # (K,)

    @classmethod
    def from_alignment(cls, alignment) -> Residual:
        """Samples of the breast (and tumour) objective of a
        :class:`regtrack.registration.align.Alignment` at its :math:`\\theta_p`."""
        th = alignment.theta_p
        pts = [alignment.breast_objective.points(th)]
        dist = [alignment.breast_objective.distances(th)]
        if alignment.tumour_objective is not None:
            pts.append(alignment.tumour_objective.points(th))
            dist.append(alignment.tumour_objective.distances(th))
        return cls(np.vstack(pts), np.concatenate(dist))


def residual_sigma(xy, residual: Residual | None, *, scale_mm: float) -> np.ndarray:
    """Locally weighted RMS registration residual (mm) at (M, 2) real-frame points."""
    xy = np.atleast_2d(np.asarray(xy, float))
    if residual is None or len(residual.distances) == 0:
        return np.zeros(len(xy))
    d2 = np.sum((xy[:, None, :] - residual.points[None]) ** 2, axis=-1)
    # subtract the row minimum before exponentiating: far points keep the nearest samples'
    # weight instead of underflowing to 0/0
    w = np.exp(-(d2 - d2.min(axis=1, keepdims=True)) / (2.0 * scale_mm ** 2))
    return np.sqrt((w * residual.distances[None] ** 2).sum(1) / w.sum(1))


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


def prediction_sigma(*, residual_mm: float, r_mm: float, theta_sigma_deg: float,
                     shift_mm: float, D: float | None, sigma_D: float, nipple_mm: float = 0.0,
                     config) -> tuple[float, dict]:
    """1-sigma radius (mm) and its four terms (module docstring); ``nipple_mm`` is
    :math:`\\sigma_{nip}`, ``config`` the :class:`~regtrack.tracking.config.TrackingConfig`."""
    rot = r_mm * math.radians(theta_sigma_deg)
    rel_D = sigma_D / D if D else 0.0
    model = abs(shift_mm) * math.hypot(rel_D, config.material_rel)
    res = max(residual_mm, config.min_residual_mm)
    nip = float(nipple_mm)
    sigma = math.sqrt(res ** 2 + rot ** 2 + model ** 2 + nip ** 2)
    return sigma, {"registration_residual": float(residual_mm), "rotation": float(rot),
                   "model": float(model), "nipple": float(nip)}


def run_direction(contour, nipple, u_mm: float) -> np.ndarray | None:
    """Unit direction (2,) of the nipple's run: the chord between the points of the open
    skin ``contour`` (M, 2) mm at arc length ``u_mm`` either side of its vertex nearest
    ``nipple`` (None when they coincide)."""
    c = np.asarray(contour, float)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    sn = s[int(np.argmin(np.linalg.norm(c - np.asarray(nipple, float), axis=1)))]
    a, b = (np.array([np.interp(x, s, c[:, 0]), np.interp(x, s, c[:, 1])])
            for x in (sn - u_mm, sn + u_mm))
    d = b - a
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-9 else None


@dataclass(frozen=True)
class NippleMoves:
    """The breast registration searched again with the real nipple moved by ``+-h`` along
    its run (module docstring, :math:`\\sigma_{nip}`): ``nipple`` / ``theta_deg`` the
    registration's :math:`n_p` and :math:`\\theta_p`, ``moved`` the two
    :math:`(n_\\pm, \\theta_\\pm)`."""

    nipple: np.ndarray
    theta_deg: float
    moved: tuple

    @classmethod
    def from_alignment(cls, alignment, real) -> NippleMoves | None:
        """For a breast-only ``alignment`` of the ``real`` view; None when its nipple was
        given or has no run (then ``u / sqrt 3`` applies, which is zero when given)."""
        u = nipple_run(real)
        n_p = np.asarray(alignment.nipple, float)
        t = run_direction(real.breast_contour, n_p, u) if u > 0.0 else None
        if t is None:
            return None
        step = u / math.sqrt(3.0) * t
        moved = tuple((n, breast_rotation(alignment, n)) for n in (n_p + step, n_p - step))
        return cls(n_p, float(alignment.theta_p), moved)

    def sigma(self, xy) -> np.ndarray:
        """:math:`\\sigma_{nip}` (M,) mm at real-frame points ``xy`` (M, 2) mm."""
        xy = np.atleast_2d(np.asarray(xy, float))
        p = [n + (xy - self.nipple) @ rotation(th - self.theta_deg).T for n, th in self.moved]
        return 0.5 * np.linalg.norm(p[0] - p[1], axis=1)


def inplane_shift(frame, reference, deformed, nipple_reference, nipple_deformed) -> np.ndarray:
    """``|Delta|`` (M,) mm: the in-plane displacement of model points (M, 3) relative to the
    nipple caused by the compression, in the plate ``frame`` (its projected position
    relative to the projected nipple, after minus before)."""
    def proj(p):
        return frame.to_local(np.atleast_2d(np.asarray(p, float)))[:, :2]

    d = (proj(deformed) - proj(nipple_deformed)) - (proj(reference) - proj(nipple_reference))
    return np.linalg.norm(d, axis=1)


@dataclass
class PredictionUncertainty:
    """The uncertainty model of one view's predictions (module docstring): what it needs
    besides a point's position and in-plane shift.

    ``residual`` the breast registration's residual samples, ``nipple`` (2,) the centre of
    rotation (real frame, mm), ``theta_sigma_deg`` the registration's angular 1-sigma,
    ``D`` / ``sigma_D`` the simulation's compression degree and its 1-sigma,
    ``nipple_run_mm`` the detector's ``u``, ``config`` the tracking settings,
    ``nipple_moves`` the registration's answer to a moved nipple (None: the prediction is
    taken to move with the nipple, :math:`\\sigma_{nip} = u / \\sqrt 3`).
    """

    residual: Residual
    nipple: np.ndarray
    theta_sigma_deg: float
    D: float | None
    sigma_D: float
    nipple_run_mm: float
    config: object = field(default=None)
    nipple_moves: NippleMoves | None = None

    @classmethod
    def from_alignment(cls, alignment, real, *, D: float | None, sigma_D: float,
                       config) -> PredictionUncertainty:
        """The model of a breast-only ``alignment`` (its objective, rotation and nipple) of
        the ``real`` view."""
        ob = alignment.breast_objective
        th = float(alignment.theta_p)
        sig = angular_sigma(ob, th, correlation_mm=config.correlation_mm,
                            spacing_mm=alignment.config.resample_mm)
        return cls(Residual(ob.points(th), ob.distances(th)), np.asarray(alignment.nipple, float),
                   sig, D, float(sigma_D), nipple_run(real), config,
                   NippleMoves.from_alignment(alignment, real))

    def at(self, xy, shift_mm) -> tuple[np.ndarray, list[dict]]:
        """1-sigma radii (M,) mm and their terms at real-frame points ``xy`` (M, 2) whose
        in-plane shifts are ``shift_mm`` (M,)."""
        xy = np.atleast_2d(np.asarray(xy, float))
        shift = np.broadcast_to(np.asarray(shift_mm, float), (len(xy),))
        res = residual_sigma(xy, self.residual, scale_mm=self.config.residual_scale_mm)
        r = np.linalg.norm(xy - self.nipple, axis=1)
        nip = (np.full(len(xy), self.nipple_run_mm / math.sqrt(3.0)) if self.nipple_moves is None
               else self.nipple_moves.sigma(xy))
        out = [prediction_sigma(residual_mm=float(res[k]), r_mm=float(r[k]),
                                theta_sigma_deg=self.theta_sigma_deg, shift_mm=float(shift[k]),
                                D=self.D, sigma_D=self.sigma_D, nipple_mm=float(nip[k]),
                                config=self.config)
               for k in range(len(xy))]
        return np.array([s for s, _ in out]), [t for _, t in out]
