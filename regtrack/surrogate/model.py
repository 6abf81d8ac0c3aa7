"""The per-patient surrogate: parameters -> nodal displacement field of one view.

:func:`fit_surrogate` compresses ``n`` simulated displacement fields of one model (same
mesh) with PCA (:mod:`.pca`) and regresses the PCA coefficients on the parameters scaled
to the design box, :math:`x_j = (p_j - \\text{lower}_j)/(\\text{upper}_j - \\text{lower}_j)`
(:mod:`.regression`).  :meth:`Surrogate.predict` returns the ``(N, 3)`` displacement (mm).

The default regressor is the Gaussian process with a linear trend and a squared-exponential
correlation (``"gp"``, ``kernel="rbf"``).  Measured on the phantom's CC view (1,825 nodes;
12 Latin-hypercube simulations over c1 in [0.27, 1.08] kPa, nu in [0.45, 0.49],
D in [0.25, 0.45]; 9 PCA modes), nodal error in mm:

==================  ===============  ================  ==========  ============
regressor           leave-one-out    4 held-out runs   fit (s)     predict (s)
                    median / p95     median / p95
==================  ===============  ================  ==========  ============
GP, RBF             0.36 / 1.24      0.17 / 0.44       1.9         0.00015
GP, Matérn 5/2      0.37 / 1.26      0.24 / 0.60       5.3         0.00019
extra trees (300)   1.19 / 3.23      0.58 / 1.56       0.34        0.033
mean field          --               2.13 / 7.84       --          --
==================  ===============  ================  ==========  ============

(2 shared cores under other load; the largest single-node error is 2 to 6 mm on the
held-out runs for every regressor.)

Saved as a folder: ``surrogate.npz`` (arrays) and ``surrogate.json`` (parameter names,
units, bounds, regressor, kernel, provenance); a tree ensemble adds ``trees.joblib``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack._io import write_json
from regtrack.errors import InputFileError
from regtrack.surrogate.pca import FieldBasis, fit_basis
from regtrack.surrogate.regression import GPCoefficients, TreeCoefficients, fit_gp, fit_trees

REGRESSORS = ("gp", "trees")
FORMAT = "regtrack-surrogate/1"


@dataclass
class Surrogate:
    """Parameters -> displacement field ``(N, 3)`` (mm) of one view of one model.

    Attributes
    ----------
    names : tuple of str
        Parameter names, in the order of :attr:`lower`/:attr:`upper` (e.g. ``c1``, ``nu``, ``D``).
    lower, upper : ndarray (d,)
        The design box the parameters are scaled by (units of each parameter).
    basis : FieldBasis
        PCA of the training fields.
    coefficients : GPCoefficients or TreeCoefficients
        Regression of the PCA coefficients on the scaled parameters.
    meta : dict
        Provenance and validation (written to the JSON as is).
    """

    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    basis: FieldBasis
    coefficients: GPCoefficients | TreeCoefficients
    meta: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return int(self.basis.mean.size // 3)

    def scaled(self, params: Any) -> np.ndarray:
        """Parameters (a mapping by name, a ``(d,)`` or ``(m, d)`` array) scaled to [0, 1]."""
        if isinstance(params, Mapping):
            missing = [n for n in self.names if n not in params]
            if missing:
                raise ValueError(f"params: missing {', '.join(missing)}; the surrogate takes "
                                 f"{', '.join(self.names)}")
            params = [float(params[n]) for n in self.names]
        p = np.atleast_2d(np.asarray(params, float))
        if p.shape[1] != len(self.names):
            raise ValueError(f"params: expected {len(self.names)} values "
                             f"({', '.join(self.names)}), got {p.shape[1]}")
        return (p - self.lower) / (self.upper - self.lower)

    def predict(self, params: Any) -> np.ndarray:
        """Displacement (mm) at ``params``: ``(N, 3)`` for one point, ``(m, N, 3)`` for ``(m, d)``.

        Outside the design box the prediction is an extrapolation (no error is raised)."""
        x = self.scaled(params)
        u = self.basis.fields(self.coefficients.predict(x)).reshape(len(x), -1, 3)
        one = isinstance(params, Mapping) or np.ndim(params) == 1
        return u[0] if one else u

    def with_fields(self, params: np.ndarray, fields: np.ndarray, *, seed: int = 0) -> Surrogate:
        """The surrogate refitted with more simulations: ``fields`` ``(m, N, 3)`` (mm) at
        ``params`` ``(m, d)`` (infill points).  The PCA basis is kept (the new fields enter
        through their coefficients on it); the Gaussian process is refitted on the old
        training points' coefficients (its posterior mean there, equal to the fitted data
        up to its nugget) and the new ones."""
        if not isinstance(self.coefficients, GPCoefficients):
            raise ValueError("with_fields: only a Gaussian-process surrogate takes infill points")
        p = np.atleast_2d(np.asarray(params, float))
        x_old = self.coefficients.x_train
        y_old = self.coefficients.predict(x_old)
        y_new = self.basis.coefficients(np.asarray(fields, float).reshape(len(p), -1))
        coeffs = fit_gp(np.vstack([x_old, self.scaled(p)]), np.vstack([y_old, y_new]),
                        kind=self.coefficients.kind, seed=seed)
        meta = {**self.meta, "infill_points": [*self.meta.get("infill_points", []), *p.tolist()]}
        return Surrogate(self.names, self.lower, self.upper, self.basis, coeffs, meta)

    def timed_predict(self, params: Any, *, repeats: int = 20) -> tuple[np.ndarray, float]:
        """:meth:`predict` and its median wall time over ``repeats`` calls (s)."""
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            u = self.predict(params)
            times.append(time.perf_counter() - t0)
        return u, float(np.median(times))

    def save(self, folder: str | Path) -> Path:
        """Write ``surrogate.npz`` + ``surrogate.json`` (+ ``trees.joblib``) into ``folder``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        arrays = {"lower": self.lower, "upper": self.upper, "mean": self.basis.mean,
                  "modes": self.basis.modes, "explained": self.basis.explained}
        doc: dict[str, Any] = {"format": FORMAT, "names": list(self.names),
                               "regressor": self.coefficients.name,
                               "n_nodes": self.n_nodes, "n_modes": self.basis.n_modes,
                               "meta": self.meta}
        if isinstance(self.coefficients, GPCoefficients):
            arrays.update(self.coefficients.arrays())
            doc["kernel"] = self.coefficients.kind
        else:
            self.coefficients.save(folder / "trees.joblib")
        np.savez(folder / "surrogate.npz", **arrays)
        return write_json(folder / "surrogate.json", doc)

    @classmethod
    def load(cls, folder: str | Path) -> Surrogate:
        """Read a surrogate written by :meth:`save`."""
        folder = Path(folder)
        js, npz = folder / "surrogate.json", folder / "surrogate.npz"
        for f in (js, npz):
            if not f.is_file():
                raise InputFileError(f"{f}: not found; build the surrogate with "
                                     "`regtrack surrogate build CASE --out DIR`")
        doc = json.loads(js.read_text(encoding="utf-8"))
        if doc.get("format") != FORMAT:
            raise InputFileError(f"{js}: format {doc.get('format')!r}, expected {FORMAT!r}; "
                                 "rebuild the surrogate with this regtrack")
        with np.load(npz) as a:
            basis = FieldBasis(a["mean"], a["modes"], a["explained"])
            coeffs: GPCoefficients | TreeCoefficients
            if doc["regressor"] == "gp":
                coeffs = GPCoefficients.from_arrays(doc["kernel"], a)
            else:
                coeffs = TreeCoefficients.load(folder / "trees.joblib")
            return cls(tuple(doc["names"]), a["lower"].copy(), a["upper"].copy(), basis, coeffs,
                       doc.get("meta", {}))


def fit_surrogate(params: np.ndarray, fields: np.ndarray, *, names: Sequence[str],
                  lower: Sequence[float], upper: Sequence[float], regressor: str = "gp",
                  kernel: str = "rbf", tol: float = 1e-4, seed: int = 0,
                  meta: dict | None = None) -> Surrogate:
    """Fit a :class:`Surrogate` to ``n`` simulations.

    Parameters
    ----------
    params : ndarray (n, d)
        Parameter points, in the order of ``names``.
    fields : ndarray (n, N, 3)
        Displacement fields (mm) of the same mesh.
    lower, upper : sequence of float
        Design box (scales the parameters to [0, 1]).
    regressor : {"gp", "trees"}
        Coefficient regression (:mod:`.regression`).
    tol : float
        Fraction of the fields' variance the PCA may leave out.
    """
    p = np.atleast_2d(np.asarray(params, float))
    u = np.asarray(fields, float)
    if u.ndim != 3 or u.shape[2] != 3 or u.shape[0] != p.shape[0]:
        raise ValueError(f"fields: expected ({p.shape[0]}, N, 3) displacements, got {u.shape}")
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    if lo.shape != (len(names),) or hi.shape != lo.shape or not np.all(hi > lo):
        raise ValueError(f"lower/upper: need {len(names)} bounds each with upper > lower")
    if regressor not in REGRESSORS:
        raise ValueError(f"regressor '{regressor}': use one of {', '.join(REGRESSORS)}")
    basis = fit_basis(u.reshape(len(u), -1), tol=tol)
    x = (p - lo) / (hi - lo)
    y = basis.coefficients(u.reshape(len(u), -1))
    coeffs = (fit_gp(x, y, kind=kernel, seed=seed) if regressor == "gp"
              else fit_trees(x, y, seed=seed))
    return Surrogate(tuple(names), lo, hi, basis, coeffs, dict(meta or {}))
