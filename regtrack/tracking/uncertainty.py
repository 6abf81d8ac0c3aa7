"""Uncertainty of a predicted position in a real mammogram (mm).

Model
-----
Two independent error sources are combined in quadrature into a 1-sigma radius

.. math::

    \\sigma = \\sqrt{\\max(\\sigma_{res}, \\sigma_{min})^2 + \\sigma_{rot}^2}

* **Registration residual** (how well the aligned virtual contours fit the real ones
  *near the point*): the locally weighted RMS of the closest-point distances ``d_i`` of
  the aligned virtual breast and tumour contour samples ``q_i`` (Lapuebla-Ferri et al.,
  eqs. 4-5, evaluated at :math:`\\theta_p`)

  .. math::

      \\sigma_{res}^2(p) = \\frac{\\sum_i w_i d_i^2}{\\sum_i w_i}, \\qquad
      w_i = \\exp\\left(-\\frac{\\lVert q_i - p\\rVert^2}{2L^2}\\right)

  with ``L`` = ``residual_scale_mm``.  A model that reproduces the real outline well
  around the point gives a small residual there.
* **Rotation ambiguity**: the breast and the tumour contours prefer different rotations
  :math:`\\theta_{p,b}` and :math:`\\theta_{p,t}`; the method applies their mean, so a
  point at distance ``r`` from the nipple (the centre of rotation) is uncertain by

  .. math:: \\sigma_{rot}(p) = r \\,\\frac{|\\theta_{p,b} - \\theta_{p,t}|}{2}
     \\quad (\\text{radians})

  the distance between its positions under :math:`\\theta_p` and either optimum.

Not modelled: the spread over the calibration's near-optimal material parameters (a
study would re-run the tracking per parameter set) and the error of the MRI annotation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


@dataclass
class Uncertainty:
    """Per-point 1-sigma radius and its two terms (mm)."""

    sigma_mm: np.ndarray
    residual_mm: np.ndarray
    rotation_mm: np.ndarray

    def to_dict(self, k: int) -> dict:
        return {"sigma_mm": float(self.sigma_mm[k]), "residual_mm": float(self.residual_mm[k]),
                "rotation_mm": float(self.rotation_mm[k])}


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


def rotation_sigma(xy, *, nipple, theta_b_deg: float, theta_t_deg: float) -> np.ndarray:
    """``r |theta_b - theta_t| / 2`` (mm) at (M, 2) real-frame points; 0 if theta_t is NaN."""
    xy = np.atleast_2d(np.asarray(xy, float))
    if not np.isfinite(theta_t_deg):
        return np.zeros(len(xy))
    r = np.linalg.norm(xy - np.asarray(nipple, float), axis=1)
    return r * np.deg2rad(abs(theta_b_deg - theta_t_deg)) / 2.0


def point_uncertainty(xy, *, residual: Residual | None, nipple, theta_b_deg: float,
                      theta_t_deg: float, scale_mm: float, floor_mm: float) -> Uncertainty:
    """1-sigma radius (mm) of predicted real-frame points (see the module docstring)."""
    res = residual_sigma(xy, residual, scale_mm=scale_mm)
    rot = rotation_sigma(xy, nipple=nipple, theta_b_deg=theta_b_deg, theta_t_deg=theta_t_deg)
    sig = np.sqrt(np.maximum(res, floor_mm) ** 2 + rot ** 2)
    return Uncertainty(sig, res, rot)
