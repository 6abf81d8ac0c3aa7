"""Sparse linear solver for the Newton corrections, chosen by measurement.

Direct solver (:mod:`.direct`): MKL PARDISO (located through pypardiso, called directly
with our own ``iparm``); ``splu`` (SuperLU, scipy) is the fallback without MKL (logged).  Every solve
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
* the matrices are symmetric (the Hessians of the incremental potential, :mod:`.minimise`):
  PARDISO factorises their upper triangle; SuperLU the whole matrix.

Because a solve costs about 1/50 of a factorisation, the factorisation is **re-used**
(``reuse_factorisation``, default on): a new matrix is first solved on the old factors
(``A P^{-1} y = b``, ``x = P^{-1} y``: the residual GMRES monitors is the true one) to the
tolerance the step solver asks for (inexact Newton).  It is refactorised when

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
import logging
import threading
import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from regtrack.mechanics.direct import LinearSolveError, Pardiso, SuperLU

log = logging.getLogger(__name__)

__all__ = ["LinearSolveError", "LinearSolver", "node_ordering", "right_gmres", "serial_openblas"]


def _cpu() -> float:
    return time.process_time()


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
        self.backend: Any = None
        self._key_factored: tuple | None = None  # the pattern analysed
        self._factored = False
        self._stale = False
        self._kept: tuple | None = None  # the pattern's entries the factorisation takes
        self.n_analyses = self.n_factorisations = self.n_krylov_solves = self.krylov_iterations = 0
        self.n_reuse_failures = self.krylov_wasted_iterations = 0
        self.time_analysis = self.time_factor_solve = self.time_krylov = 0.0
        self.cpu_factor = 0.0
        self.cpu_krylov_iteration = 0.0
        self.cost_ratio = 8.0  # factorisation / GMRES iteration, estimated at each factorisation
        if kind in ("auto", "pardiso"):
            try:
                self.backend = Pardiso(single=precision == "mixed")
                self.kind = "pardiso"
            except (ImportError, OSError) as exc:
                if kind == "pardiso":
                    from regtrack.errors import ConfigError

                    raise ConfigError(f"[mechanics.solver] linear_solver = 'pardiso': not available ({exc}); "
                                      "install pypardiso or use 'splu'") from exc
                log.warning("PARDISO not available (%s): falling back to SuperLU (slower)", exc)
                self.kind = "splu"
        if self.kind == "splu":
            self.backend = SuperLU()

    # -- public -------------------------------------------------------------------------
    def solve(self, A: sp.csr_matrix, b: np.ndarray, *, rtol: float | None = None,
              refactor: bool = False) -> np.ndarray:
        """Solve the symmetric system ``A x = b`` to ``||A x - b|| <= rtol ||b||``.

        ``rtol``: the caller's tolerance (inexact Newton), floored at ``krylov_rtol``
        (its default); ``refactor`` forces a fresh factorisation.
        Raises :class:`LinearSolveError` when the factorisation fails.
        """
        b = np.asarray(b, float)
        tol = self.krylov_rtol if rtol is None else max(rtol, self.krylov_rtol)
        key = self._key(A)
        same = self._key_factored == key and self._factored
        if self.reuse and same and not refactor and not self._stale:
            k0 = self.krylov_iterations
            x = self._krylov(A, b, tol, fresh=False)
            if x is not None:
                return x
            self.n_reuse_failures += 1
            self.krylov_wasted_iterations += self.krylov_iterations - k0
        t0 = time.perf_counter()
        self._factorise(A, key)
        x = self._krylov(A, b, tol, fresh=True)
        if x is None and self.backend.single:
            log.warning("float32 factorisation too inaccurate for this system (ill-conditioned): "
                        "switching the linear solver to double precision")
            self._to_double()
            self._factorise(A, key)
            x = self._krylov(A, b, tol, fresh=True)
        self.time_factor_solve += time.perf_counter() - t0
        if x is None:
            raise LinearSolveError(f"linear solve did not reach the relative residual {tol:.1e} on a fresh "
                                   "factorisation (singular or extremely ill-conditioned tangent)")
        return x

    def inertia(self) -> tuple[int, int] | None:
        """``(positive, negative)`` eigenvalue counts of the last symmetric (LDL^T)
        factorisation (PARDISO ``iparm(22)``, ``iparm(23)``), or None (SuperLU)."""
        be = self.backend
        if not isinstance(be, Pardiso) or not self._factored:
            return None
        return int(be.iparm[21]), int(be.iparm[22])

    def release(self) -> None:
        """Free the factorisation memory."""
        self.backend.free()
        self._key_factored = None
        self._factored = False

    @property
    def factor_nnz(self) -> int:
        """Non-zeros of the largest factor (PARDISO's iparm(18))."""
        return int(getattr(self.backend, "factor_nnz", 0))

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

    def _factored_matrix(self, A: sp.csr_matrix, key: tuple) -> sp.csr_matrix:
        """The matrix the backend factorises: ``A`` less the entries of :meth:`_drop`, and
        for PARDISO only its upper triangle (``A`` is symmetric); the positions kept are
        cached per pattern."""
        if self._kept is None or self._kept[0] != key:
            n = A.shape[0]
            rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
            cols = A.indices.astype(np.int64)
            keep = ~self._drop(rows, cols, n)
            if self.kind == "pardiso":
                keep &= cols >= rows
            keep = np.flatnonzero(keep)
            indptr = np.zeros(n + 1, np.int32)
            np.cumsum(np.bincount(rows[keep], minlength=n), out=indptr[1:])
            self._kept = (key, keep, cols[keep].astype(np.int32), indptr)
        _, keep, idx, ptr = self._kept
        M = sp.csr_matrix((A.data[keep], idx, ptr), shape=A.shape, copy=False)
        M.has_sorted_indices = True
        return M

    def _to_double(self) -> None:
        self.backend.free()
        self.backend = Pardiso(single=False)
        self._key_factored = None
        self._factored = False
        self.precision = "double"

    def _factorise(self, A: sp.csr_matrix, key: tuple) -> None:
        be = self.backend
        self._key(A)  # A's arrays are the ones remembered for the next call
        M = self._factored_matrix(A, key)
        if key != self._key_factored:
            t0 = time.perf_counter()
            if self._key_factored is not None:
                be.free()
            be.analyse(M, self._order(M))
            self._key_factored = key
            self.n_analyses += 1
            self.time_analysis += time.perf_counter() - t0
        c0 = _cpu()
        self._factored = False
        be.factorise(M)
        self._factored = True
        self._stale = False
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

    def _krylov(self, A: sp.csr_matrix, b: np.ndarray, rtol: float, *,
                fresh: bool) -> np.ndarray | None:
        """GMRES preconditioned by the stored factorisation; None if it does not reach
        ``rtol`` within :meth:`_k_max` iterations."""
        be = self.backend
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
                self._stale = k > 0.25 * self.cost_ratio
            log.debug("%s factorisation: %d GMRES iterations to %.1e (asked %.1e), %.3f s CPU%s",
                      "fresh" if fresh else "re-used", k, res / nb, rtol, cpu,
                      " (stale)" if self._stale else "")
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
