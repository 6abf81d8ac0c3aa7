"""Principal components of nodal displacement snapshots (the surrogate's field compression).

The ``n`` snapshots :math:`u_i \\in \\mathbb{R}^{3N}` (one simulation each, flattened
``(N, 3)`` displacements in mm) are centred on their mean :math:`\\bar u` and decomposed by a
thin SVD, :math:`U - \\bar u = A\\,S\\,V^T`.  A field is then
:math:`u \\approx \\bar u + \\sum_k a_k v_k`, with the coefficients :math:`a = (U-\\bar u) V`
(mm).  The kept modes are the fewest whose squared singular values explain at least
``1 - tol`` of the total variance, and never more than ``n - 1`` (the centred snapshots
span at most ``n - 1`` dimensions).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FieldBasis:
    """A truncated PCA basis of displacement fields.

    Attributes
    ----------
    mean : ndarray, shape (3N,)
        Mean snapshot (mm).
    modes : ndarray, shape (r, 3N)
        Orthonormal principal directions (rows; dimensionless).
    explained : ndarray, shape (r,)
        Fraction of the snapshots' variance each kept mode explains.
    """

    mean: np.ndarray
    modes: np.ndarray
    explained: np.ndarray

    @property
    def n_modes(self) -> int:
        return int(self.modes.shape[0])

    def coefficients(self, fields: np.ndarray) -> np.ndarray:
        """Coefficients (mm) of ``fields`` (``(m, 3N)``) on the modes: ``(m, r)``."""
        return (np.asarray(fields, float) - self.mean) @ self.modes.T

    def fields(self, coeffs: np.ndarray) -> np.ndarray:
        """Fields ``(m, 3N)`` (mm) of the coefficients ``(m, r)``."""
        return self.mean + np.asarray(coeffs, float) @ self.modes


def fit_basis(snapshots: np.ndarray, *, tol: float = 1e-4) -> FieldBasis:
    """PCA basis of ``snapshots`` (``(n, 3N)``, mm) keeping ``1 - tol`` of the variance.

    Raises
    ------
    ValueError
        Fewer than two snapshots, or ``tol`` outside (0, 1).
    """
    x = np.asarray(snapshots, float)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"snapshots: expected (n >= 2, 3N) fields, got shape {x.shape}")
    if not 0.0 < tol < 1.0:
        raise ValueError(f"tol = {tol}: must be in (0, 1)")
    mean = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    var = s**2
    total = float(var.sum())
    if total <= 0.0:  # every snapshot identical: the mean is the whole model
        return FieldBasis(mean, np.zeros((0, x.shape[1])), np.zeros(0))
    frac = var / total
    r = int(np.searchsorted(np.cumsum(frac), 1.0 - tol) + 1)
    r = min(r, x.shape[0] - 1, int(np.count_nonzero(var > total * 1e-24)))
    return FieldBasis(mean, vt[:r].copy(), frac[:r].copy())
