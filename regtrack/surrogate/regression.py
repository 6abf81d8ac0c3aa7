"""Regression of the PCA coefficients on the scaled parameters.

Two regressors, compared by leave-one-out error on the phantom (:mod:`.validate`):

* :class:`GPCoefficients` (the default) -- per PCA mode, a linear trend in the scaled
  parameters plus a Gaussian process on the trend's residual (universal kriging):

  .. math:: a_k(x) = \\beta_{k0} + \\beta_k^T x + r_k(x), \\qquad
            r_k \\sim \\mathcal{GP}\\big(0,\\ \\sigma_k^2\\, \\rho(\\lVert (x-x')/\\ell_k
            \\rVert) + \\eta_k^2 \\delta_{xx'}\\big),

  with :math:`x \\in [0, 1]^d` the parameters scaled to the design box, an anisotropic
  squared-exponential (or Matérn 5/2) correlation with one length scale per parameter,
  and a white-noise term :math:`\\eta_k^2` (solver tolerance).  The squared-exponential
  correlation is the default: its leave-one-out error on the phantom is slightly below the
  Matérn's (:mod:`.model` has the numbers).  The hyperparameters are
  fitted by scikit-learn's :class:`~sklearn.gaussian_process.GaussianProcessRegressor`
  (maximum marginal likelihood, Rasmussen & Williams 2006, ch. 5); the prediction is the
  posterior mean :math:`\\beta_{k0} + \\beta_k^T x + s_k\\, k(x, X)\\,\\alpha_k`, evaluated
  from stored arrays (the kernel rebuilt from its fitted length scales), so the saved
  surrogate holds no pickled objects.  The trend
  makes a field that is linear in the parameters exact, and the displacement is close to
  linear in the compression degree D.
* :class:`TreeCoefficients` -- an extremely randomised tree ensemble
  (:class:`~sklearn.ensemble.ExtraTreesRegressor`; Geurts et al. 2006), the regressor of
  Martínez-Martínez et al. (2017) for breast compression, fitted on all coefficients at once.
  Saved with joblib (scikit-learn's persistence), the only pickle in a surrogate.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

KERNELS = ("rbf", "matern52")


def correlation(kind: str, x: np.ndarray, y: np.ndarray, length_scales: np.ndarray) -> np.ndarray:
    """Correlation matrix ``(len(x), len(y))`` of the anisotropic ``kind`` kernel:
    scikit-learn's ``RBF`` (``exp(-d^2/2)``) or ``Matern(nu=2.5)``, with ``d = |(x - y) / l|``,
    rebuilt from the stored length scales ``l``."""
    from sklearn.gaussian_process.kernels import RBF, Matern

    if kind == "rbf":
        kernel = RBF(length_scale=length_scales)
    elif kind == "matern52":
        kernel = Matern(length_scale=length_scales, nu=2.5)
    else:
        raise ValueError(f"kernel '{kind}': use one of {', '.join(KERNELS)}")
    return kernel(np.asarray(x, float), np.asarray(y, float))


def _trend_matrix(x: np.ndarray) -> np.ndarray:
    return np.hstack([np.ones((len(x), 1)), np.asarray(x, float)])


@dataclass
class GPCoefficients:
    """Linear trend + one Gaussian process per PCA mode (see the module docstring).

    Attributes
    ----------
    kind : str
        Correlation, ``"matern52"`` or ``"rbf"``.
    x_train : ndarray (n, d)
        Scaled training parameters (in [0, 1]).
    trend : ndarray (d + 1, r)
        Least-squares trend coefficients (intercept first; mm).
    scale : ndarray (r,)
        Standard deviation of each mode's trend residual (mm); 0 where the trend is exact.
    amplitude : ndarray (r,)
        GP signal variance :math:`\\sigma_k^2` of the standardised residual.
    length_scales : ndarray (r, d)
        Length scale per mode and parameter (scaled units).
    alpha : ndarray (n, r)
        :math:`(K + \\eta^2 I)^{-1} y` of each mode's standardised residual.
    """

    kind: str
    x_train: np.ndarray
    trend: np.ndarray
    scale: np.ndarray
    amplitude: np.ndarray
    length_scales: np.ndarray
    alpha: np.ndarray

    name = "gp"

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Coefficients ``(m, r)`` (mm) at the scaled parameters ``x`` (``(m, d)``)."""
        x = np.atleast_2d(np.asarray(x, float))
        out = _trend_matrix(x) @ self.trend
        for k in range(out.shape[1]):
            if self.scale[k] > 0.0:
                kx = correlation(self.kind, x, self.x_train, self.length_scales[k])
                out[:, k] += self.scale[k] * self.amplitude[k] * (kx @ self.alpha[:, k])
        return out

    def arrays(self) -> dict[str, np.ndarray]:
        return {"gp_x_train": self.x_train, "gp_trend": self.trend, "gp_scale": self.scale,
                "gp_amplitude": self.amplitude, "gp_length_scales": self.length_scales,
                "gp_alpha": self.alpha}

    @classmethod
    def from_arrays(cls, kind: str, arrays: Any) -> GPCoefficients:
        return cls(kind, *(np.asarray(arrays[f"gp_{k}"], float) for k in
                           ("x_train", "trend", "scale", "amplitude", "length_scales", "alpha")))


def fit_gp(x: np.ndarray, y: np.ndarray, *, kind: str = "rbf", restarts: int = 3,
           seed: int = 0) -> GPCoefficients:
    """Fit :class:`GPCoefficients` to scaled parameters ``x`` (``(n, d)``) and coefficients
    ``y`` (``(n, r)``, mm)."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, Matern, WhiteKernel

    if kind not in KERNELS:
        raise ValueError(f"kernel '{kind}': use one of {', '.join(KERNELS)}")
    x = np.asarray(x, float)
    y = np.asarray(y, float).reshape(len(x), -1)
    n, d = x.shape
    r = y.shape[1]
    h = _trend_matrix(x)
    trend = np.linalg.lstsq(h, y, rcond=None)[0]
    resid = y - h @ trend
    scale = resid.std(axis=0)
    amplitude = np.zeros(r)
    length = np.ones((r, d))
    alpha = np.zeros((n, r))
    tiny = 1e-10 * max(float(np.abs(y).max(initial=0.0)), 1e-300)
    for k in range(r):
        if scale[k] <= tiny:  # the trend is exact for this mode
            scale[k] = 0.0
            continue
        corr = (Matern(length_scale=np.full(d, 0.5), length_scale_bounds=(1e-2, 1e3), nu=2.5)
                if kind == "matern52" else
                RBF(length_scale=np.full(d, 0.5), length_scale_bounds=(1e-2, 1e3)))
        kernel = (ConstantKernel(1.0, (1e-4, 1e3)) * corr
                  + WhiteKernel(1e-4, noise_level_bounds=(1e-10, 1e-1)))
        gp = GaussianProcessRegressor(kernel=kernel, normalize_y=False,
                                      n_restarts_optimizer=restarts, random_state=seed)
        with warnings.catch_warnings():  # a bound reached is the answer, not a failure
            warnings.simplefilter("ignore")
            gp.fit(x, resid[:, k] / scale[k])
        amplitude[k] = gp.kernel_.k1.k1.constant_value
        length[k] = np.broadcast_to(gp.kernel_.k1.k2.length_scale, (d,))
        alpha[:, k] = np.ravel(gp.alpha_)
    return GPCoefficients(kind, x, trend, scale, amplitude, length, alpha)


@dataclass
class TreeCoefficients:
    """Extra-trees regression of all coefficients at once (see the module docstring)."""

    model: Any  # sklearn.ensemble.ExtraTreesRegressor

    name = "trees"

    def predict(self, x: np.ndarray) -> np.ndarray:
        out = self.model.predict(np.atleast_2d(np.asarray(x, float)))
        return out.reshape(out.shape[0], -1)

    def save(self, path: Path) -> None:
        import joblib

        joblib.dump(self.model, path)

    @classmethod
    def load(cls, path: Path) -> TreeCoefficients:
        import joblib

        return cls(joblib.load(path))


def fit_trees(x: np.ndarray, y: np.ndarray, *, n_trees: int = 300, seed: int = 0) -> TreeCoefficients:
    """Fit :class:`TreeCoefficients` (``n_trees`` fully grown extra trees, one thread)."""
    from sklearn.ensemble import ExtraTreesRegressor

    model = ExtraTreesRegressor(n_estimators=n_trees, random_state=seed, n_jobs=1)
    model.fit(np.asarray(x, float), np.asarray(y, float).reshape(len(x), -1))
    return TreeCoefficients(model)
