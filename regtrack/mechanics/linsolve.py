"""Sparse linear solver for the Newton corrections, chosen by measurement.

``pardiso`` (MKL PARDISO through pypardiso) is the default: symmetric indefinite
LDL^T (mtype -2, upper triangle; about 1.6-2x faster than LU here) for symmetric
tangents, general LU with pivot perturbation (mtype 11) when a contribution (friction)
makes the tangent unsymmetric.  It was the fastest direct solver on this machine it was the fastest direct solver (DESIGN.md; see
``pipelines/bench_mechanics.py``).  Its symbolic analysis (ordering + fill pattern) is
done once per sparsity pattern and re-used by every later factorisation, because the
assembly keeps one fixed pattern.  ``splu`` (SuperLU from scipy) is the pure-scipy
fallback, used when MKL is not available (logged once).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

log = logging.getLogger(__name__)


class LinearSolver:
    """Solve ``A x = b`` for CSR matrices sharing a pattern; times each phase.

    Parameters
    ----------
    kind : {"auto", "pardiso", "splu"}
    """

    def __init__(self, kind: str = "auto") -> None:
        self.kind = kind
        self._pardiso = None
        self._pattern_key: tuple | None = None
        self._sym_key: tuple | None = None
        self._upper: tuple | None = None
        self.n_analyses = 0
        self.n_factorisations = 0
        self.time_analysis = 0.0
        self.time_factor_solve = 0.0
        if kind in ("auto", "pardiso"):
            try:
                import pypardiso

                self._pardiso = pypardiso.PyPardisoSolver(mtype=11)
                self._pardiso_sym = pypardiso.PyPardisoSolver(mtype=-2)
                self.kind = "pardiso"
            except (ImportError, OSError) as exc:
                if kind == "pardiso":
                    from regtrack.errors import ConfigError

                    raise ConfigError(f"[mechanics.solver] linear_solver = 'pardiso': not available ({exc}); "
                                      "install pypardiso or use 'splu'") from exc
                log.warning("PARDISO not available (%s): falling back to SuperLU (slower)", exc)
                self.kind = "splu"

    def solve(self, A: sp.csr_matrix, b: np.ndarray, *, symmetric: bool = False) -> np.ndarray:
        """Factorise ``A`` (re-using the analysis of its pattern) and solve for ``b``.

        ``symmetric=True`` promises ``A == A.T`` (then only its upper triangle is used).
        """
        if self.kind == "splu":
            t0 = time.perf_counter()
            x = spla.splu(A.tocsc()).solve(b)
            self.time_factor_solve += time.perf_counter() - t0
            self.n_factorisations += 1
            return x
        if symmetric:
            return self._solve_symmetric(A, b)
        return self._solve_pardiso(A, b)

    @staticmethod
    def _key(A: sp.csr_matrix) -> tuple:
        return (A.shape[0], A.nnz, id(A.indices), A.indices[:: max(1, A.nnz // 64)].tobytes())

    def _solve_symmetric(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        key = self._key(A)
        if self._upper is None or self._upper[0] != key:
            rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
            up = np.flatnonzero(A.indices >= rows)
            indptr = np.zeros(A.shape[0] + 1, np.int64)
            np.cumsum(np.bincount(rows[up], minlength=A.shape[0]), out=indptr[1:])
            self._upper = (key, up, A.indices[up].copy(), indptr)
        _, up, idx, ptr = self._upper
        U = sp.csr_matrix((A.data[up], idx, ptr), shape=A.shape, copy=False)
        U.has_sorted_indices = True
        return self._solve_pardiso(U, b, solver=self._pardiso_sym, attr="_sym_key")

    def _solve_pardiso(self, A: sp.csr_matrix, b: np.ndarray, *, solver=None,
                       attr: str = "_pattern_key") -> np.ndarray:
        ps = solver or self._pardiso
        key = self._key(A)
        ps._check_A(A)
        b = np.asfortranarray(b, dtype=float)
        if key != getattr(self, attr):
            t0 = time.perf_counter()
            ps.set_phase(11)
            ps._call_pardiso(A, b)
            setattr(self, attr, key)
            self.n_analyses += 1
            self.time_analysis += time.perf_counter() - t0
        t0 = time.perf_counter()
        ps.set_phase(23)
        x = ps._call_pardiso(A, b)
        self.time_factor_solve += time.perf_counter() - t0
        self.n_factorisations += 1
        return np.asarray(x).reshape(b.shape)

    def release(self) -> None:
        """Free the factorisation memory."""
        if self._pardiso is not None:
            for ps, attr in ((self._pardiso, "_pattern_key"), (self._pardiso_sym, "_sym_key")):
                if getattr(self, attr) is not None:
                    ps.free_memory(everything=True)
                    setattr(self, attr, None)
