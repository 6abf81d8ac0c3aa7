"""Sparse linear solver for the Newton corrections, chosen by measurement.

``pardiso`` (MKL PARDISO through pypardiso, general LU with pivot perturbation, so it
also takes the indefinite / unsymmetric tangents of contact with friction) is the
default: on this machine it was the fastest direct solver (DESIGN.md; see
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
        self.n_analyses = 0
        self.n_factorisations = 0
        self.time_analysis = 0.0
        self.time_factor_solve = 0.0
        if kind in ("auto", "pardiso"):
            try:
                import pypardiso

                self._pardiso = pypardiso.PyPardisoSolver(mtype=11)
                self.kind = "pardiso"
            except (ImportError, OSError) as exc:
                if kind == "pardiso":
                    from regtrack.errors import ConfigError

                    raise ConfigError(f"[mechanics.solver] linear_solver = 'pardiso': not available ({exc}); "
                                      "install pypardiso or use 'splu'") from exc
                log.warning("PARDISO not available (%s): falling back to SuperLU (slower)", exc)
                self.kind = "splu"

    def solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        """Factorise ``A`` (re-using the analysis of its pattern) and solve for ``b``."""
        if self.kind == "splu":
            t0 = time.perf_counter()
            x = spla.splu(A.tocsc()).solve(b)
            self.time_factor_solve += time.perf_counter() - t0
            self.n_factorisations += 1
            return x
        return self._solve_pardiso(A, b)

    def _solve_pardiso(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        ps = self._pardiso
        key = (A.shape[0], A.nnz, id(A.indices), A.indices[:: max(1, A.nnz // 64)].tobytes())
        ps._check_A(A)
        b = np.asfortranarray(b, dtype=float)
        if key != self._pattern_key:
            t0 = time.perf_counter()
            ps.set_phase(11)
            ps._call_pardiso(A, b)
            self._pattern_key = key
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
        if self._pardiso is not None and self._pattern_key is not None:
            self._pardiso.free_memory(everything=True)
            self._pattern_key = None
