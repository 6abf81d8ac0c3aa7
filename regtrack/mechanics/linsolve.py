"""Sparse linear solver for the Newton corrections, chosen by measurement.

Direct solver: MKL PARDISO (located through pypardiso, called directly with our own
``iparm``); ``splu`` (SuperLU, scipy) is the fallback without MKL (logged).  Every solve
is right-preconditioned GMRES (:func:`right_gmres`) on a stored factorisation, to the
relative residual the caller asks for.  The design choices, each with its reason (figures
in docs/performance-mechanics.md):

* LDL^T (``mtype -2``) throughout: not slower than Cholesky on the same matrix, and it
  survives the indefinite tangents of contact and buckling.  The ANP system ``[[K, B^T],
  [B, -D]]`` is quasi-definite, so no weighted matching or scaling (they made the analysis
  1.6x slower); pivot perturbation 1e-8.
* float32 factors refined by float64 GMRES (``precision = "mixed"``, ``iparm(28) = 1``):
  about 1.7x faster factorisations and half the memory; their solutions have a relative
  residual ~1e-4, so GMRES reaches 1e-10 in 2-3 iterations.  If a fresh float32
  factorisation cannot bring its own matrix to the tolerance, the solver switches to
  float64 for good (logged).
* ordering (``ordering = "nodes"``): METIS nested dissection of the *node* graph, each
  node's unknowns eliminated together (:func:`node_ordering`, handed to PARDISO as
  ``perm``), with the couplings of the chest-wall (Dirichlet) dofs left out of the
  factorised matrix (``decoupled``): factorisations 27-30 % faster than PARDISO's own METIS
  on the dof graph (``ordering = "pardiso"``).
* unsymmetric tangents (sliding friction) are solved by GMRES preconditioned with LDL^T
  factors of a symmetric matrix of the same pattern (one analysis; the factors stay valid
  while the stick/slip state flips): the caller's ``preconditioner`` (the tangent without
  the sliding nodes' friction-bound term,
  :meth:`regtrack.mechanics.contact.PlateContact.preconditioner_tangent`: the
  preconditioned operator is the identity plus node-local rank-one terms, 1-4 GMRES
  iterations), else the symmetric part ``(A + A^T) / 2``.  Only if a fresh factorisation
  cannot reach the tolerance does the solver switch to LU (``mtype 11``), which costs
  about 5x an LDL^T factorisation.

Because a solve costs about 1/50 of a factorisation, the factorisation is **re-used**
(``reuse_factorisation``, default on): a new matrix is first solved on the old factors
(``A P^{-1} y = b``, ``x = P^{-1} y``: the residual GMRES monitors is the true one) to the
tolerance the Newton solver asks for (inexact Newton).  It is refactorised when

* GMRES does not reach ``rtol`` within ``k_max = clip(b rho, 4, krylov_max)`` iterations,
  with the budget ``b = reuse_budget`` (0.5: a failed attempt wastes at most half a
  factorisation), or
* the previous re-used solve already cost more than a quarter of a factorisation
  (``k > rho / 4``: the preconditioner has gone stale).

``rho``, the cost of a factorisation in GMRES iterations, is estimated from the factor
size, not timed, so that the Newton path does not depend on the machine's load:

.. math::

    \\rho = 2.2 \\sqrt{\\mathrm{nnz}(L) / (2 n)}

a fit to float32 factorisations against GMRES iterations (solve + product) measured on
7.5k to 53k unknowns.  The operation count ``nnz(L) / (2 n)`` overestimates it 4-8x,
because the supernodal factorisation runs at BLAS-3 speed and the triangular solves are
memory-bound.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import threading
import time
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numba import njit

log = logging.getLogger(__name__)

# MKL's conditional numerical reproducibility: without it, PARDISO's threaded factorisation
# sums in a load-dependent order, the Newton path of a contact problem changes in the last
# digits from run to run, and a hard increment converges in one run and not in the next
# (measured: the same CC protocol stopped at t = 0.6817 and 0.6801).  Read when MKL loads.
os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")


_SERIAL = {"lock": threading.Lock(), "depth": 0, "limiter": None}


@contextlib.contextmanager
def serial_openblas():
    """Run numpy's and scipy's OpenBLAS on one thread inside the block (a context manager
    and, called, a decorator); MKL, i.e. PARDISO, keeps its threads.

    With PARDISO in strict CNR mode (above) the Newton path then no longer depends on the
    machine's core count.  OpenBLAS splits a dot product (or a norm) of more than 10,000
    entries across its threads, and each split sums in another order: on the 9,496-node
    benchmark hemisphere (28k-entry vectors) the default two threads took the CC
    compression along another path than one thread (383 against 343 Newton iterations),
    and the frictional pinch problems amplify such last-digit differences
    into different plate forces.  Below 10,000 entries OpenBLAS uses one thread anyway,
    so the small models' results are unchanged.

    The limit is process-wide (threadpoolctl), so it is counted: the first block to enter
    sets it and the last to leave restores the caller's setting, also when blocks of
    several threads overlap (simulations sharing a Dask worker process); other numpy work
    of the process runs on one OpenBLAS thread meanwhile.
    """
    st = _SERIAL
    with st["lock"]:
        if st["depth"] == 0:
            from threadpoolctl import ThreadpoolController

            st["limiter"] = ThreadpoolController().select(internal_api="openblas").limit(limits=1)
        st["depth"] += 1
    try:
        yield
    finally:
        with st["lock"]:
            st["depth"] -= 1
            if st["depth"] == 0:
                st["limiter"].restore_original_limits()
                st["limiter"] = None


#: iparm (0-based) shared by both matrix types; see the module docstring.
_IPARM_COMMON = {0: 1, 1: 2, 7: 0, 17: -1, 20: 1, 23: 0, 26: 0, 34: 1}
_IPARM = {-2: {9: 8, 10: 0, 12: 0}, 11: {9: 13, 10: 1, 12: 1}}


class LinearSolveError(RuntimeError):
    """The sparse direct solver failed (singular matrix, out of memory); the Newton solver
    treats it like a failed increment and cuts back."""


def _cpu() -> float:
    return time.process_time()


_PARDISO_FN: list = []


def _pardiso_function():
    """MKL's ``pardiso`` entry point, located once per process by pypardiso (its search of
    the environment's directory tree took ~0.6 s per solver object here).

    pypardiso looks for ``mkl_rt`` with ``ctypes.util.find_library`` and then by a
    recursive glob of the whole environment, once when imported and once more per solver
    object: 0.32 s per process here, of a benchmark CC of about 58 s.  Unless
    ``PYPARDISO_MKL_RT`` names the library already, the places where the ``mkl`` wheel
    installs it (``<prefix>/lib``, ``<prefix>/Library/bin``) are looked at first and
    handed over in that variable (then 3 ms); if nothing is there, pypardiso searches as
    before."""
    if not _PARDISO_FN:
        if not os.environ.get("PYPARDISO_MKL_RT"):
            import glob
            import sys

            found = [p for pattern in ("lib/libmkl_rt.so*", "lib/libmkl_rt*.dylib",
                                       "Library/bin/mkl_rt*.dll")
                     for p in glob.glob(os.path.join(sys.prefix, pattern))]
            if found:
                os.environ["PYPARDISO_MKL_RT"] = sorted(found, key=lambda p: (len(p), p))[-1]
        import pypardiso

        _PARDISO_FN.append(pypardiso.PyPardisoSolver()._mkl_pardiso)
    return _PARDISO_FN[0]


class _Pardiso:
    """One MKL PARDISO instance of one matrix type; ``single`` factorises in float32."""

    def __init__(self, mtype: int, *, single: bool = False):
        self._fn = _pardiso_function()
        self.mtype = mtype
        self.single = single
        self.perm = np.zeros(1, np.int32)  # a user fill-reducing ordering when iparm(5) = 1
        self.pt = np.zeros(64, np.int64)
        self.iparm = np.zeros(64, np.int32)
        for k, v in {**_IPARM_COMMON, **_IPARM[mtype]}.items():
            self.iparm[k] = v
        self.iparm[27] = int(single)
        self.M: sp.csr_matrix | None = None
        self.alive = False

    def _call(self, phase: int, M: sp.csr_matrix, b: np.ndarray | None = None) -> np.ndarray:
        n = M.shape[0]
        dt = np.float32 if self.single else np.float64
        b = np.zeros(n, dt) if b is None else np.ascontiguousarray(b, dt)
        x = np.zeros_like(b)
        data = np.ascontiguousarray(M.data, dt)
        indptr = M.indptr if M.indptr.dtype == np.int32 else M.indptr.astype(np.int32)
        indices = M.indices if M.indices.dtype == np.int32 else M.indices.astype(np.int32)
        err = ctypes.c_int32(0)
        i32 = ctypes.POINTER(ctypes.c_int32)
        vp = ctypes.c_void_p
        self._fn(self.pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ctypes.byref(ctypes.c_int32(1)),
                 ctypes.byref(ctypes.c_int32(1)), ctypes.byref(ctypes.c_int32(self.mtype)),
                 ctypes.byref(ctypes.c_int32(phase)), ctypes.byref(ctypes.c_int32(n)),
                 data.ctypes.data_as(vp), indptr.ctypes.data_as(i32), indices.ctypes.data_as(i32),
                 self.perm.ctypes.data_as(i32), ctypes.byref(ctypes.c_int32(1)),
                 self.iparm.ctypes.data_as(i32), ctypes.byref(ctypes.c_int32(0)), b.ctypes.data_as(vp),
                 x.ctypes.data_as(vp), ctypes.byref(err))
        if err.value != 0:
            raise LinearSolveError(f"PARDISO (mtype {self.mtype}) phase {phase} failed with error "
                                   f"{err.value} (-4: zero pivot, -2: out of memory)")
        return x.astype(np.float64, copy=False)

    def analyse(self, M: sp.csr_matrix, order: np.ndarray | None = None) -> None:
        """Symbolic analysis; ``order``: the unknowns in elimination order (``order[k]`` is
        eliminated k-th), else PARDISO's own METIS ordering of the dof graph."""
        self.iparm[4] = int(order is not None)
        self.perm = np.zeros(1, np.int32) if order is None else np.ascontiguousarray(order, np.int32)
        self._call(11, M)
        self.alive = True

    def factorise(self, M: sp.csr_matrix) -> None:
        self.M = M if not self.single else sp.csr_matrix((M.data.astype(np.float32), M.indices, M.indptr),
                                                         shape=M.shape, copy=False)
        self._call(22, self.M)

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._call(33, self.M, b)

    @property
    def factor_nnz(self) -> int:
        return int(self.iparm[17])

    def free(self) -> None:
        if self.alive:
            self._call(-1, sp.csr_matrix((1, 1)) if self.M is None else self.M)
        self.pt[:] = 0  # a fresh handle for the next analysis
        self.alive = False
        self.M = None


class _SuperLU:
    """scipy SuperLU with the same interface (full matrix, no separate analysis; its own
    COLAMD ordering)."""

    single = False

    def __init__(self):
        self.lu = None
        self.M = None
        self.factor_nnz = 0

    def analyse(self, M, order=None) -> None:
        pass

    def factorise(self, M) -> None:
        try:
            self.lu = spla.splu(M.tocsc())
        except RuntimeError as exc:
            raise LinearSolveError(f"SuperLU failed: {exc}") from exc
        self.M = M
        self.factor_nnz = self.lu.L.nnz + self.lu.U.nnz

    def solve(self, b):
        return self.lu.solve(np.asarray(b, float))

    def free(self) -> None:
        self.lu = self.M = None


class LinearSolver:
    """Solve ``A x = b`` for CSR matrices sharing a pattern; counts and times each phase.

    Every solve is right-preconditioned GMRES (:func:`right_gmres`) on a stored
    factorisation, to the relative residual the caller asks for; the factorisation is
    renewed as described in the module docstring.

    Parameters
    ----------
    kind : {"auto", "pardiso", "splu"}
    reuse_factorisation : keep a factorisation across matrices while that is cheaper;
        ``False``: factorise every matrix (then solved to ``krylov_rtol``: exact Newton).
    precision : {"mixed", "double"}: PARDISO factorisation in float32 (``mixed``,
        default; GMRES in float64 restores full accuracy) or float64.  ``mixed`` falls
        back to ``double`` for good (logged) if a fresh float32 factorisation cannot
        bring its own matrix to the tolerance (ill-conditioned system).
    krylov_rtol : relative residual of a solve when the caller gives none, and the floor
        of the caller's tolerance.
    krylov_max : cap of the GMRES iterations before refactorising.
    reuse_budget : GMRES budget of a solve on a re-used factorisation, as a fraction of the
        cost ratio (``k_max = clip(reuse_budget * rho, 4, krylov_max)``).
    dof_nodes : mesh node of each unknown (``3 p + k`` -> ``p``; an ANP pressure -> its
        node); with ``ordering = "nodes"`` the fill-reducing ordering is METIS nested
        dissection of the node graph, each node's unknowns kept together
        (:func:`node_ordering`).  Without it, or with ``ordering = "pardiso"``, PARDISO
        orders the dof graph itself.
    decoupled : unknowns whose rows and columns the caller keeps zero but for the diagonal
        in every matrix it passes (Dirichlet dofs replaced by identity rows).  Their
        off-diagonal pattern entries are left out of the factorised matrix, so they do not
        couple their neighbours in the elimination (GMRES still multiplies by the full
        ``A``: a broken promise costs GMRES iterations or fails a solve, never gives a wrong
        answer).  Measured on the 10.5k-node hemisphere (3,702 fixed dofs): factor
        non-zeros 24.3 M instead of 27.6 M, factorisation 0.39 s instead of 0.43 s.

    Attributes: ``n_analyses``, ``n_factorisations``, ``n_krylov_solves`` (solves on a
    factorisation of an earlier matrix), ``krylov_iterations`` (all GMRES iterations),
    ``n_reuse_failures`` (re-used factorisations that could not reach the tolerance within
    their budget, then refactorised) and ``krylov_wasted_iterations`` (their iterations);
    wall times ``time_analysis``, ``time_factor_solve`` (factorisation + first solve),
    ``time_krylov`` (s); CPU times ``cpu_factor`` (last factorisation) and
    ``cpu_krylov_iteration`` (running mean per GMRES iteration), s.
    """

    def __init__(self, kind: str = "auto", *, reuse_factorisation: bool = True, precision: str = "mixed",
                 krylov_rtol: float = 1e-10, krylov_max: int = 60, reuse_budget: float = 0.5,
                 ordering: str = "nodes",
                 dof_nodes: np.ndarray | None = None, decoupled: np.ndarray | None = None) -> None:
        self.kind = kind
        self.decoupled = None if decoupled is None else np.unique(np.asarray(decoupled, np.int64))
        self.ordering = ordering
        self.dof_nodes = dof_nodes
        self.time_ordering = 0.0
        self.reuse = reuse_factorisation
        self.precision = precision
        self.krylov_rtol = krylov_rtol
        self.krylov_max = krylov_max
        self.reuse_budget = reuse_budget
        self._backends: dict[bool, object] = {}
        self._keys: dict[bool, tuple | None] = {True: None, False: None}
        self._factored: dict[bool, bool] = {True: False, False: False}
        self._stale: dict[bool, bool] = {True: False, False: False}
        self._upper: tuple | None = None
        self._full: tuple | None = None
        self._lu_needed = False
        self._pre: Any = None  # this solve's preconditioning matrix, or a function making it
        self.n_analyses = self.n_factorisations = self.n_krylov_solves = self.krylov_iterations = 0
        self.n_reuse_failures = self.krylov_wasted_iterations = 0
        self.time_analysis = self.time_factor_solve = self.time_krylov = 0.0
        self.cpu_factor = 0.0
        self.cpu_krylov_iteration = 0.0
        self.cost_ratio = 8.0  # factorisation / GMRES iteration, estimated at each factorisation
        if kind in ("auto", "pardiso"):
            try:
                single = precision == "mixed"
                self._backends = {False: _Pardiso(11, single=single), True: _Pardiso(-2, single=single)}
                self.kind = "pardiso"
            except (ImportError, OSError) as exc:
                if kind == "pardiso":
                    from regtrack.errors import ConfigError

                    raise ConfigError(f"[mechanics.solver] linear_solver = 'pardiso': not available ({exc}); "
                                      "install pypardiso or use 'splu'") from exc
                log.warning("PARDISO not available (%s): falling back to SuperLU (slower)", exc)
                self.kind = "splu"
        if self.kind == "splu":
            self._backends = {False: _SuperLU(), True: _SuperLU()}

    # -- public -------------------------------------------------------------------------
    def solve(self, A: sp.csr_matrix, b: np.ndarray, *, symmetric: bool = False,
              rtol: float | None = None, refactor: bool = False,
              preconditioner: sp.csr_matrix | None = None) -> np.ndarray:
        """Solve ``A x = b`` to ``||A x - b|| <= rtol ||b||``; ``symmetric=True`` promises
        ``A == A.T``.

        ``rtol``: the caller's tolerance (inexact Newton), floored at ``krylov_rtol``
        (its default); ``refactor`` forces a fresh factorisation.
        ``preconditioner``: for an unsymmetric ``A``, a matrix of the same pattern whose
        symmetric part is factorised (LDL^T) in place of ``A``'s own symmetric part
        (ignored when the patterns differ, or once LU is in use), or a function that
        assembles it, called only if this solve factorises.
        Raises :class:`LinearSolveError` when the factorisation fails.
        """
        b = np.asarray(b, float)
        tol = self.krylov_rtol if rtol is None else max(rtol, self.krylov_rtol)
        key = self._key(A)
        self._pre = None if symmetric else preconditioner
        # handle True: LDL^T of the symmetric part (A itself when symmetric); False: LU
        sym = self.kind == "pardiso" and (symmetric or (not self._lu_needed
                                                        and self._upper_map(A, key)[4] is not None))
        same = self._keys[sym] == key and self._factored[sym]
        if self.reuse and same and not refactor and not self._stale[sym]:
            k0 = self.krylov_iterations
            x = self._krylov(A, b, sym, tol, fresh=False)
            if x is not None:
                return x
            self.n_reuse_failures += 1
            self.krylov_wasted_iterations += self.krylov_iterations - k0
        t0 = time.perf_counter()
        self._factorise(A, sym, key)
        x = self._krylov(A, b, sym, tol, fresh=True)
        if x is None and sym and not symmetric:
            log.info("unsymmetric tangent too far from its symmetric part to precondition with it: "
                     "general LU from now on")
            self._lu_needed = True
            sym = False
            self._factorise(A, sym, key)
            x = self._krylov(A, b, sym, tol, fresh=True)
        if x is None and self._backends[sym].single:
            log.warning("float32 factorisation too inaccurate for this system (ill-conditioned): "
                        "switching the linear solver to double precision")
            self._to_double()
            self._factorise(A, sym, key)
            x = self._krylov(A, b, sym, tol, fresh=True)
        self.time_factor_solve += time.perf_counter() - t0
        if x is None:
            raise LinearSolveError(f"linear solve did not reach the relative residual {tol:.1e} on a fresh "
                                   "factorisation (singular or extremely ill-conditioned tangent)")
        return x

    def inertia(self) -> tuple[int, int] | None:
        """``(positive, negative)`` eigenvalue counts of the last symmetric (LDL^T)
        factorisation (PARDISO ``iparm(22)``, ``iparm(23)``), or None (SuperLU, LU)."""
        be = self._backends.get(True)
        if not isinstance(be, _Pardiso) or not self._factored.get(True):
            return None
        return int(be.iparm[21]), int(be.iparm[22])

    def release(self) -> None:
        """Free the factorisation memory."""
        for sym, be in self._backends.items():
            be.free()
            self._keys[sym] = None
            self._factored[sym] = False

    @property
    def factor_nnz(self) -> int:
        """Non-zeros of the largest factor (PARDISO's iparm(18))."""
        return max(int(getattr(be, "factor_nnz", 0)) for be in self._backends.values())

    # -- internals ----------------------------------------------------------------------
    def _key(self, A: sp.csr_matrix) -> tuple:
        """Identity of a sparsity pattern: a full hash (a wrong match would corrupt PARDISO),
        skipped when ``A``'s index arrays are views of the very same memory as those of the
        last matrix (the solver's fixed layout: scipy wraps the layout's arrays in new
        views for every matrix, so the views differ but their base arrays do not; the
        bases are kept referenced, so their identity cannot be recycled).  The hash cost
        ~10 ms per Newton iteration at 38k unknowns (1.4 % of the 10k-node CC run)."""
        import hashlib

        last = getattr(self, "_last_pattern", None)
        ident = (_memory_id(A.indices), _memory_id(A.indptr))
        if last is not None and ident[0] == last[0] and ident[1] == last[1]:
            return last[2]
        key = (A.shape[0], A.nnz, hashlib.blake2b(np.ascontiguousarray(A.indices).view(np.uint8),
                                                  digest_size=16).digest(),
               hashlib.blake2b(np.ascontiguousarray(A.indptr).view(np.uint8), digest_size=16).digest())
        self._last_pattern = (*ident, key, A.indices, A.indptr)
        return key

    def _drop(self, rows: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
        """Pattern entries (of an ``n``-unknown matrix) left out of the factorised matrix:
        the off-diagonal ones of the ``decoupled`` unknowns (zero by the caller's promise)."""
        if self.decoupled is None:
            return np.zeros(len(rows), bool)
        dec = np.zeros(n, bool)
        dec[self.decoupled[self.decoupled < n]] = True
        return (dec[rows] | dec[cols]) & (rows != cols)

    def _pruned(self, A: sp.csr_matrix, key: tuple) -> sp.csr_matrix:
        """``A`` without the entries of :meth:`_drop` (the matrix an LU factorises)."""
        if self.decoupled is None:
            return A
        if self._full is None or self._full[0] != key:
            n = A.shape[0]
            rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
            keep = np.flatnonzero(~self._drop(rows, A.indices.astype(np.int64), n))
            indptr = np.zeros(n + 1, np.int32)
            np.cumsum(np.bincount(rows[keep], minlength=n), out=indptr[1:])
            self._full = (key, keep, A.indices[keep].astype(np.int32), indptr)
        _, keep, idx, ptr = self._full
        M = sp.csr_matrix((A.data[keep], idx, ptr), shape=A.shape, copy=False)
        M.has_sorted_indices = True
        return M

    def _upper_map(self, A: sp.csr_matrix, key: tuple) -> tuple:
        """``(key, up, indices, indptr, tmap)`` of the upper triangle of A's pattern less
        the entries of :meth:`_drop`: ``up`` the positions of its entries in ``A.data``,
        ``tmap`` those of their transposes (None when the pattern is not structurally
        symmetric); cached per pattern."""
        if self._upper is None or self._upper[0] != key:
            n = A.shape[0]
            rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
            cols = A.indices.astype(np.int64)
            up = np.flatnonzero((cols >= rows) & ~self._drop(rows, cols, n))
            indptr = np.zeros(n + 1, np.int32)
            np.cumsum(np.bincount(rows[up], minlength=n), out=indptr[1:])
            keys = rows * n + cols  # sorted: rows ascending, sorted column indices
            tpos = np.searchsorted(keys, cols[up] * n + rows[up])
            tpos = np.minimum(tpos, len(keys) - 1)
            tmap = tpos if np.array_equal(keys[tpos], cols[up] * n + rows[up]) else None
            self._upper = (key, up, cols[up].astype(np.int32), indptr, tmap)
        return self._upper

    def _upper_sym(self, A: sp.csr_matrix, key: tuple) -> sp.csr_matrix | None:
        """Upper triangle of the symmetric part ``(A + A^T) / 2`` on A's own pattern less
        the entries of :meth:`_drop`, or None when that pattern is not structurally
        symmetric."""
        _, up, idx, ptr, tmap = self._upper_map(A, key)
        if tmap is None:
            return None
        U = sp.csr_matrix((_half_sum(A.data, up, tmap), idx, ptr), shape=A.shape, copy=False)
        U.has_sorted_indices = True
        return U

    def _to_double(self) -> None:
        for sym, be in list(self._backends.items()):
            be.free()
            self._backends[sym] = _Pardiso(be.mtype, single=False)
            self._keys[sym] = None
            self._factored[sym] = False
        self.precision = "double"

    def _preconditioner(self, key: tuple) -> sp.csr_matrix | None:
        """The caller's preconditioning matrix (assembled now if given as a function), or
        None when there is none or its pattern is not ``key``'s."""
        pre = self._pre
        if callable(pre):
            pre = self._pre = pre()
        if pre is None:
            return None
        if self._key(pre) != key:
            log.debug("preconditioning matrix of another pattern: ignored")
            pre = self._pre = None
        return pre

    def _factorise(self, A: sp.csr_matrix, sym: bool, key: tuple) -> None:
        be = self._backends[sym]
        pre = self._preconditioner(key) if sym else None
        self._key(A)  # A's arrays are the ones remembered for the next call
        if sym:
            M = self._upper_sym(A if pre is None else pre, key)
        else:
            M = self._pruned(A, key)
        if key != self._keys[sym]:
            t0 = time.perf_counter()
            if self._keys[sym] is not None:
                be.free()
            be.analyse(M, self._order(M))
            self._keys[sym] = key
            self.n_analyses += 1
            self.time_analysis += time.perf_counter() - t0
        c0 = _cpu()
        self._factored[sym] = False
        be.factorise(M)
        self._factored[sym] = True
        self._stale[sym] = False
        self.cpu_factor = _cpu() - c0
        self.n_factorisations += 1
        fnnz = int(getattr(be, "factor_nnz", 0)) or 20 * M.nnz
        self.cost_ratio = max(2.2 * np.sqrt(fnnz / (2.0 * M.shape[0])), 16.0)

    def _order(self, M: sp.csr_matrix) -> np.ndarray | None:
        """The node-blocked elimination order of ``M``'s pattern, or None (PARDISO's own)."""
        if self.ordering != "nodes" or self.dof_nodes is None or self.kind != "pardiso":
            return None
        if len(self.dof_nodes) != M.shape[0]:
            log.warning("dof_nodes has %d entries for a %d-unknown system: PARDISO's own ordering",
                        len(self.dof_nodes), M.shape[0])
            return None
        t0 = time.perf_counter()
        try:
            order = node_ordering(M, self.dof_nodes)
        except ImportError as exc:  # pymetis is a dependency; a broken install still solves
            log.warning("pymetis not available (%s): PARDISO's own ordering (slower factorisation)", exc)
            self.ordering = "pardiso"
            return None
        self.time_ordering += time.perf_counter() - t0
        return order

    def _k_max(self, fresh: bool) -> int:
        if fresh:
            return self.krylov_max
        return int(np.clip(self.reuse_budget * self.cost_ratio, 4, self.krylov_max))

    def _krylov(self, A: sp.csr_matrix, b: np.ndarray, sym: bool, rtol: float, *,
                fresh: bool) -> np.ndarray | None:
        """GMRES preconditioned by the stored factorisation; None if it does not reach
        ``rtol`` within :meth:`_k_max` iterations."""
        be = self._backends[sym]
        nb = _norm(b)
        if nb == 0.0:
            return np.zeros_like(b)
        t0, c0 = time.perf_counter(), _cpu()
        x, k = right_gmres(lambda v: A @ v, be.solve, b, rtol=rtol, max_iterations=self._k_max(fresh))
        cpu = _cpu() - c0
        self.krylov_iterations += k
        if not fresh:
            per = cpu / max(k, 1)
            self.cpu_krylov_iteration = per if self.cpu_krylov_iteration == 0 else \
                0.7 * self.cpu_krylov_iteration + 0.3 * per
            self.time_krylov += time.perf_counter() - t0
        res = _norm(A @ x - b)
        if res <= rtol * nb * (1 + 1e-6) and np.all(np.isfinite(x)):
            if not fresh:
                self.n_krylov_solves += 1
                self._stale[sym] = k > 0.25 * self.cost_ratio
            log.debug("%s factorisation: %d GMRES iterations to %.1e (asked %.1e), %.3f s CPU%s",
                      "fresh" if fresh else "re-used", k, res / nb, rtol, cpu,
                      " (stale)" if self._stale[sym] else "")
            return x
        log.debug("%s factorisation: GMRES reached %.1e (asked %.1e) in %d iterations", "fresh" if fresh
                  else "re-used", res / nb, rtol, k)
        return None


def node_ordering(A: sp.csr_matrix, dof_nodes: np.ndarray) -> np.ndarray:
    """Fill-reducing elimination order of ``A`` by nested dissection of its *node* graph.

    The quotient graph (node p ~ node q when an unknown of p couples with one of q in
    ``A``'s pattern, either triangle) is ordered by METIS (pymetis, its default options:
    deterministic), and each node's unknowns are eliminated together in their index order.
    Returns ``order`` with ``order[k]`` the unknown eliminated k-th (PARDISO's ``perm``
    with ``iparm(5) = 1``).

    Why: PARDISO's METIS on the dof graph separates a node's 3 displacements and its ANP
    pressure from one another, so its supernodes are narrower.  Measured on the 10.5k-node
    hemisphere (ANP, 42,103 unknowns, float32 LDL^T, 2 threads): factor non-zeros 27.6 M
    instead of 28.9 M, 39.4 GFlop instead of 40.6, factorisation 0.44 s instead of 0.54 s
    (90 GFlop/s instead of 76), symbolic analysis 0.10 s instead of 0.30 s, METIS 0.08 s.
    """
    import pymetis

    nn = int(dof_nodes.max()) + 1
    rows = np.repeat(dof_nodes, np.diff(A.indptr))
    cols = dof_nodes[A.indices]
    off = rows != cols
    r, c = np.concatenate([rows[off], cols[off]]), np.concatenate([cols[off], rows[off]])
    Q = sp.csr_matrix((np.ones(len(r), np.int8), (r, c)), shape=(nn, nn))
    Q.sum_duplicates()
    graph = pymetis.CSRAdjacency(Q.indptr.astype(np.int64), Q.indices.astype(np.int64))
    perm, _ = pymetis.nested_dissection(graph)
    rank = np.empty(nn, np.int64)
    rank[np.asarray(perm)] = np.arange(nn)
    return np.lexsort((np.arange(len(dof_nodes)), rank[dof_nodes])).astype(np.int32)


@njit(cache=True)
def _half_sum(data, up, tmap):
    """``0.5 * (data[up] + data[tmap])`` in one pass (the values of the symmetric part)."""
    out = np.empty(up.shape[0])
    for j in range(up.shape[0]):
        out[j] = 0.5 * (data[up[j]] + data[tmap[j]])
    return out


def _memory_id(a: np.ndarray) -> tuple:
    """(identity of the base array, data address, shape, strides) of an index array: equal
    for two views of the same memory with the same extent.  The caller keeps a reference
    to the view, hence to its base, so that identity cannot be recycled."""
    base = a
    while isinstance(base.base, np.ndarray):
        base = base.base
    return (id(base), a.__array_interface__["data"][0], a.shape, a.strides)


def _norm(v: np.ndarray) -> float:
    """2-norm without BLAS (see :func:`right_gmres`)."""
    return float(np.sqrt(np.einsum("i,i->", v, v)))


def right_gmres(matvec, precondition, b: np.ndarray, *, rtol: float,
                max_iterations: int) -> tuple[np.ndarray, int]:
    """Right-preconditioned GMRES (no restart) for ``A x = b`` from ``x0 = 0``.

    Builds the Krylov basis ``V`` of ``A P^{-1}`` and keeps ``Z = P^{-1} V`` (flexible
    GMRES storage: no extra preconditioner solve at the end), so the residual it
    minimises, ``|b - A x|``, is the true one.  Classical Gram-Schmidt applied twice (as
    accurate as modified Gram-Schmidt) with numpy ``einsum`` loops (OpenBLAS's threaded
    gemv/dot cost ~10x more CPU with other jobs on the cores); Givens rotations give the
    residual norm.  Stops below ``rtol |b|`` or after ``max_iterations``.  Written here
    because scipy's ``gmres`` preconditions from the left and its Python loop cost ~2x a
    PARDISO solve per iteration (measured at 42k unknowns).

    Returns ``(x, iterations)``.
    """
    n = len(b)
    m = max(int(max_iterations), 1)
    beta = _norm(b)
    V = np.empty((m + 1, n))
    Z = np.empty((m, n))
    H = np.zeros((m + 1, m))
    cs = np.zeros(m)
    sn = np.zeros(m)
    g = np.zeros(m + 1)
    g[0] = beta
    V[0] = b / beta
    k = 0
    for j in range(m):
        Z[j] = precondition(V[j])
        w = matvec(Z[j])
        Vj = V[: j + 1]
        h = np.einsum("ij,j->i", Vj, w)
        w -= np.einsum("i,ij->j", h, Vj)
        h2 = np.einsum("ij,j->i", Vj, w)
        w -= np.einsum("i,ij->j", h2, Vj)
        H[: j + 1, j] = h + h2
        H[j + 1, j] = _norm(w)
        if H[j + 1, j] > 0:
            V[j + 1] = w / H[j + 1, j]
        for i in range(j):  # previous rotations
            a, c = H[i, j], H[i + 1, j]
            H[i, j], H[i + 1, j] = cs[i] * a + sn[i] * c, -sn[i] * a + cs[i] * c
        r = float(np.hypot(H[j, j], H[j + 1, j]))
        cs[j], sn[j] = (1.0, 0.0) if r == 0 else (H[j, j] / r, H[j + 1, j] / r)
        H[j, j], H[j + 1, j] = r, 0.0
        g[j + 1] = -sn[j] * g[j]
        g[j] = cs[j] * g[j]
        k = j + 1
        if abs(g[j + 1]) <= rtol * beta or r == 0:
            break
    if k == 0 or H[k - 1, k - 1] == 0:
        return np.zeros(n), k
    z = np.linalg.solve(np.triu(H[:k, :k]), g[:k])
    return np.einsum("i,ij->j", z, Z[:k]), k
