"""The sparse direct solvers behind :class:`.linsolve.LinearSolver`: MKL PARDISO, called
directly with our own ``iparm`` (located through pypardiso), and SuperLU (scipy), the
fallback without MKL.  Both offer ``analyse(M, order)``, ``factorise(M)``, ``solve(b)``,
``factor_nnz`` and ``free()``.
"""

from __future__ import annotations

import ctypes
import os

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

# MKL's conditional numerical reproducibility: without it, PARDISO's threaded factorisation
# sums in a load-dependent order, the Newton path of a contact problem changes in the last
# digits from run to run, and a hard increment converges in one run and not in the next
# (measured: the same CC protocol stopped at t = 0.6817 and 0.6801).  Read when MKL loads.
os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")


#: iparm (0-based) of the symmetric indefinite factorisation (the choices: :mod:`.linsolve`).
_IPARM = {0: 1, 1: 2, 7: 0, 9: 8, 10: 0, 12: 0, 17: -1, 20: 1, 23: 0, 26: 0, 34: 1}


class LinearSolveError(RuntimeError):
    """The sparse direct solver failed (singular matrix, out of memory); the step solver
    corrects the Hessian or cuts the increment back."""


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


class Pardiso:
    """One MKL PARDISO instance (real symmetric indefinite, ``mtype -2``: LDL^T of the upper
    triangle); ``single`` factorises in float32."""

    mtype = -2

    def __init__(self, *, single: bool = False):
        self._fn = _pardiso_function()
        self.single = single
        self.perm = np.zeros(1, np.int32)  # a user fill-reducing ordering when iparm(5) = 1
        self.pt = np.zeros(64, np.int64)
        self.iparm = np.zeros(64, np.int32)
        for k, v in _IPARM.items():
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


class SuperLU:
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
