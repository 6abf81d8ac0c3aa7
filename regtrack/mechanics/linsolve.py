"""Sparse linear solver for the Newton corrections, chosen by measurement.

``pardiso`` (MKL PARDISO through pypardiso) is the default: symmetric indefinite LDL^T
(mtype -2, upper triangle) for symmetric systems, general LU with pivot perturbation
(mtype 11) when a contribution (friction) makes the tangent unsymmetric.  It was the
fastest direct solver here (DESIGN.md; ``pipelines/bench_mechanics.py``), ahead of
SuperLU and AMG-CG, whose iteration counts double between nu = 0.45 and 0.49.

Two re-uses keep the cost down, since the assembly keeps one fixed pattern:

* the symbolic analysis (ordering, fill pattern) is done once per pattern;
* optionally (``reuse_factorisation``, off by default: on a 2k-node hemisphere the
  PARDISO solve phase cost ~1/3 of a factorisation and GMRES needed ~15 of them, 5x
  slower overall) the last numeric factorisation preconditions GMRES on the new
  matrix; the correction is accepted only when the *true* residual satisfies
  ``||A x - b|| <= krylov_rtol ||b||`` (default 1e-10, so Newton stays quadratic) within
  ``krylov_max`` iterations, else the matrix is refactorised and solved directly.

``splu`` (SuperLU from scipy) is the pure-scipy fallback when MKL is not available
(logged once).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

log = logging.getLogger(__name__)


class LinearSolver:
    """Solve ``A x = b`` for CSR matrices sharing a pattern; counts and times each phase.

    Parameters
    ----------
    kind : {"auto", "pardiso", "splu"}
    reuse_factorisation : precondition GMRES with the previous factorisation.
    krylov_rtol, krylov_max : acceptance tolerance and iteration cap of that GMRES.
    """

    def __init__(self, kind: str = "auto", *, reuse_factorisation: bool = False,
                 krylov_rtol: float = 1e-10, krylov_max: int = 25) -> None:
        self.kind = kind
        self.reuse = reuse_factorisation
        self.krylov_rtol = krylov_rtol
        self.krylov_max = krylov_max
        self._solvers: dict[bool, object] = {}
        self._keys: dict[bool, tuple | None] = {True: None, False: None}
        self._factored: dict[bool, sp.csr_matrix | None] = {True: None, False: None}
        self._upper: tuple | None = None
        self.n_analyses = 0
        self.n_factorisations = 0
        self.n_krylov_solves = 0
        self.krylov_iterations = 0
        self.time_analysis = 0.0
        self.time_factor_solve = 0.0
        self.time_krylov = 0.0
        if kind in ("auto", "pardiso"):
            try:
                import pypardiso

                self._solvers = {False: pypardiso.PyPardisoSolver(mtype=11),
                                 True: pypardiso.PyPardisoSolver(mtype=-2)}
                self.kind = "pardiso"
            except (ImportError, OSError) as exc:
                if kind == "pardiso":
                    from regtrack.errors import ConfigError

                    raise ConfigError(f"[mechanics.solver] linear_solver = 'pardiso': not available ({exc}); "
                                      "install pypardiso or use 'splu'") from exc
                log.warning("PARDISO not available (%s): falling back to SuperLU (slower)", exc)
                self.kind = "splu"

    def solve(self, A: sp.csr_matrix, b: np.ndarray, *, symmetric: bool = False,
              rtol: float | None = None, refactor: bool = False) -> np.ndarray:
        """Solve ``A x = b``; ``symmetric=True`` promises ``A == A.T`` (upper triangle used).

        ``rtol`` overrides ``krylov_rtol`` for a re-used factorisation (inexact Newton);
        ``refactor`` forces a fresh factorisation.
        """
        b = np.asarray(b, float)
        if self.kind == "splu":
            t0 = time.perf_counter()
            x = spla.splu(A.tocsc()).solve(b)
            self.time_factor_solve += time.perf_counter() - t0
            self.n_factorisations += 1
            return x
        M = self._upper_triangle(A) if symmetric else A
        key = self._key(M)
        if (self.reuse and not refactor and self._keys[symmetric] == key
                and self._factored[symmetric] is not None):
            x = self._krylov(A, b, symmetric, self.krylov_rtol if rtol is None else max(rtol, self.krylov_rtol))
            if x is not None:
                return x
        return self._factor_solve(M, b, symmetric, key)

    @staticmethod
    def _key(A: sp.csr_matrix) -> tuple:
        """Identity of a sparsity pattern (a full hash: a wrong match would corrupt PARDISO)."""
        import hashlib

        return (A.shape[0], A.nnz, hashlib.blake2b(np.ascontiguousarray(A.indices).view(np.uint8),
                                                   digest_size=16).digest(),
                hashlib.blake2b(np.ascontiguousarray(A.indptr).view(np.uint8), digest_size=16).digest())

    def _upper_triangle(self, A: sp.csr_matrix) -> sp.csr_matrix:
        key = self._key(A)
        if self._upper is None or self._upper[0] != key:
            rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
            up = np.flatnonzero(A.indices >= rows)
            indptr = np.zeros(A.shape[0] + 1, A.indices.dtype)
            np.cumsum(np.bincount(rows[up], minlength=A.shape[0]), out=indptr[1:])
            self._upper = (key, up, A.indices[up].copy(), indptr)
        _, up, idx, ptr = self._upper
        U = sp.csr_matrix((A.data[up], idx, ptr), shape=A.shape, copy=False)
        U.has_sorted_indices = True
        return U

    def _call(self, symmetric: bool, M: sp.csr_matrix, b: np.ndarray, phase: int) -> np.ndarray:
        ps = self._solvers[symmetric]
        ps.set_phase(phase)
        return np.asarray(ps._call_pardiso(M, np.asfortranarray(b))).reshape(b.shape)

    def _factor_solve(self, M: sp.csr_matrix, b: np.ndarray, symmetric: bool, key: tuple) -> np.ndarray:
        ps = self._solvers[symmetric]
        ps._check_A(M)
        if key != self._keys[symmetric]:
            t0 = time.perf_counter()
            self._call(symmetric, M, b, 11)
            self._keys[symmetric] = key
            self.n_analyses += 1
            self.time_analysis += time.perf_counter() - t0
        t0 = time.perf_counter()
        x = self._call(symmetric, M, b, 23)
        self.time_factor_solve += time.perf_counter() - t0
        self.n_factorisations += 1
        self._factored[symmetric] = M
        return x

    def _krylov(self, A: sp.csr_matrix, b: np.ndarray, symmetric: bool, rtol: float) -> np.ndarray | None:
        """GMRES preconditioned by the stored factorisation; None if not accurate enough."""
        t0 = time.perf_counter()
        F = self._factored[symmetric]
        prec = spla.LinearOperator(A.shape, matvec=lambda r: self._call(symmetric, F, np.asarray(r, float), 33))
        count = [0]

        def cb(_):
            count[0] += 1

        nb = float(np.linalg.norm(b))
        # left preconditioning: GMRES monitors the preconditioned residual, so aim lower and
        # judge by the true residual below
        x, _ = spla.gmres(A, b, M=prec, rtol=min(1e-15, rtol * 1e-5), atol=0.0, restart=self.krylov_max,
                          maxiter=1, callback=cb, callback_type="pr_norm")
        self.time_krylov += time.perf_counter() - t0
        self.krylov_iterations += count[0]
        if nb == 0.0 or np.linalg.norm(A @ x - b) <= rtol * nb:
            self.n_krylov_solves += 1
            return x
        log.debug("stale factorisation: GMRES did not reach %.1e in %d iterations; refactorising",
                  rtol, self.krylov_max)
        return None

    def release(self) -> None:
        """Free the factorisation memory."""
        for sym, ps in self._solvers.items():
            if self._keys[sym] is not None:
                ps.free_memory(everything=True)
                self._keys[sym] = None
                self._factored[sym] = None
