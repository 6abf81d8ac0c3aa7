"""Newton minimisation of the incremental potential at fixed loads and contact lags.

One increment of a load step (:mod:`.minimise`) minimises ``Pi(u)`` (N mm) over the free
dofs with the plates' multipliers and friction lag held; this module is that
minimisation.

Newton's method with a guaranteed descent (Nocedal & Wright, *Numerical Optimization*,
2nd ed., sections 3.4 and 6.3; as IPC, Li et al. 2020):

* the Hessian is first the consistent tangent with the contact blocks projected onto the
  positive semi-definite cone (:mod:`.potential`); it is made positive definite by
  *inertia correction*: the LDL^T factorisation reports its inertia, which for the ANP
  saddle-point system ``[[K, B^T], [B, -D]]`` must show exactly one negative eigenvalue
  per pressure group (Haynsworth: the condensed ``K + B^T D^-1 B`` is then positive
  definite); otherwise each tetrahedron's material tangent ``dP/dF`` (9x9) is projected
  onto the positive semi-definite cone (its negative eigenvalues clamped to zero, in
  closed form; Teran et al. 2005, Smith et al. 2019, as in IPC), which gives that inertia
  by construction and corrects only the elements that are indefinite (a shift ``tau I``
  remains for a singular projected Hessian);
* a correction computed on an earlier (positive definite) factorisation is accepted only
  if it is a descent direction, ``R . du < 0``;
* the outer surface's self-contact barrier (:mod:`.selfcontact`), when the problem has
  one, joins the potential with its positive semi-definite Hessian, whose couplings beyond
  the mesh's pattern extend the system matrix; the line search starts from the largest
  step in which no node can cross a triangle (its additive CCD);
* the step length is chosen by backtracking on the potential itself (Armijo: ``Pi(u + a
  du) <= Pi(u) + c a R . du``); an inverted element makes ``Pi`` infinite;
* an increment has converged when the residual ``R = dPi/du`` on the free dofs meets
  ``||R||_2 <= force_tol F_ref``, its resultant ``|sum R|`` is below ``balance_tol`` of
  the largest load, *and* the Newton correction from there moves no node by more than
  ``disp_abs_tol_mm`` (0.01 mm): a small residual alone leaves a soft mode (a node sliding
  on the frictionless chest wall, a wrinkle) undetermined by millimetres, and with it the
  result dependent on rounding.

Every iteration lowers ``Pi``, which is bounded below (elastic energy grows without bound,
gravity is linear, contact is non-negative), so the iterates converge to a stationary
point: no merit-function switching, no acceptance of a stalled iterate.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from regtrack.errors import SolverDidNotConvergeError
from regtrack.mechanics.linsolve import LinearSolveError, LinearSolver
from regtrack.mechanics.potential import PlateEval, PlatePotential
from regtrack.mechanics.problem import (FORCE_FLOOR_N, Problem, chest_wall_reaction,
                                        constraint_positions, dof_nodes, evaluate, scatter_add,
                                        system_matrix)
from regtrack.mechanics.selfcontact import BarrierEval, Pairs
from regtrack.mechanics.types import StepStats

log = logging.getLogger(__name__)

#: Armijo's sufficient-decrease constant.
ARMIJO_C = 1e-4
#: A full Newton step lowering the potential by more than this times the quadratic
#: model's prediction is extended (:meth:`Minimiser.line_search`).
EXPAND_RATIO = 1.5
#: Relative tolerance of a Newton correction solved on an earlier factorisation (inexact
#: Newton: GMRES stops at 1 % of the residual; a fresh factorisation solves to 1e-10).
FORCING = 1e-2


@dataclass
class NewtonState:
    """Potential, residual and (optionally) the assembled pieces at one ``u``."""

    u: np.ndarray
    energy: float
    R: np.ndarray
    plates: list[PlateEval]
    ev: object = None
    f_ref: float = 0.0
    skin: BarrierEval | None = None


class Minimiser:
    """Newton minimisation of the incremental potential for one problem (module docstring).

    Parameters
    ----------
    problem : the discrete problem (:func:`.problem.build_problem`).
    options : :class:`.config.SolverOptions` (``force_tol``, ``max_iterations``,
        ``max_augmentations``, the linear-solver settings).
    fixed_dofs : the dofs held at their value (default: the model's fixed nodes).
    """

    def __init__(self, problem: Problem, options, fixed_dofs: np.ndarray | None = None) -> None:
        self.p = problem
        self.o = options
        self.ls = _linear_solver(problem, options)
        self.fixed_dofs = problem.fixed_dofs if fixed_dofs is None else np.unique(fixed_dofs)
        self.free = np.ones(problem.n_dofs, bool)
        self.free[self.fixed_dofs] = False
        self._diag = problem.pattern.diagonal_positions()
        self._cons = constraint_positions(problem, self.fixed_dofs)
        self.n_groups = 0 if problem.groups is None else problem.groups.n_groups
        self.barrier = problem.self_contact
        self._pairs: np.ndarray | None = None  # node pairs coupled so far, keys i * N + j
        self._coupled: tuple | None = None  # the system matrix's pattern with their blocks
        # every iteration lowers the potential, so a minimisation may take longer than a
        # Newton solve of the residual before an increment is halved
        self.max_iterations = 4 * options.max_iterations
        self.stats = StepStats()
        #: whether the last line search took the whole Newton step (or more)
        self.full_step = False
        #: called after every Newton iteration (progress of a long increment), or None
        self.on_iteration: Callable[[], None] | None = None

    # -- the potential ------------------------------------------------------------------
    def state(self, u: np.ndarray, fext: np.ndarray, plates: Sequence[PlatePotential], *,
              hessian: bool, pairs: Pairs | None = None) -> NewtonState | None:
        """``Pi``, ``R = dPi/du`` and the pieces of the Hessian at ``u`` (None if an element
        inverts or the barrier is infinite); ``pairs``: the self-contact pairs to evaluate
        (default: those within the barrier's reach at ``u``)."""
        t0 = time.perf_counter()
        ev = evaluate(self.p, u, want_k=hessian)
        if ev.n_inverted != 0 or not np.all(np.isfinite(ev.f)):
            self.stats.t_assembly += time.perf_counter() - t0
            return None
        ue = np.asarray(u, float).reshape(-1)
        energy = ev.energy - float(fext @ ue)
        R = ev.f - fext
        pe = [pl.evaluate(u, hessian=hessian) for pl in plates]
        fc = 0.0
        for e in pe:
            energy += e.energy
            R = R + e.grad
            fc = max(fc, float(np.linalg.norm(e.grad.reshape(-1, 3).sum(axis=0))))
        skin = None
        if self.barrier is not None:
            skin = self.barrier.evaluate(ue, pairs, hessian=hessian)
            if not np.isfinite(skin.energy):
                self.stats.t_assembly += time.perf_counter() - t0
                return None
            energy += skin.energy
            R = R + skin.grad
        self.stats.t_assembly += time.perf_counter() - t0
        weight = float(np.linalg.norm(fext.reshape(-1, 3).sum(axis=0)))
        reaction = float(np.linalg.norm(chest_wall_reaction(self.p, ue, R)))
        f_ref = max(weight, fc, reaction, float(np.linalg.norm(ev.f)) / np.sqrt(len(ev.f)),
                    FORCE_FLOOR_N)
        return NewtonState(ue.reshape(-1, 3), energy, R, pe, ev, f_ref, skin)

    def converged(self, s: NewtonState, scale: float = 1.0) -> bool:
        """Whether the residual and its resultant meet ``scale`` times their tolerances."""
        norm = float(np.linalg.norm(s.R[self.free]))
        resultant = float(np.linalg.norm(self.free_resultant(s.R)))
        return (norm <= scale * self.o.force_tol * s.f_ref
                and resultant <= scale * self.o.balance_tol * s.f_ref)

    def free_resultant(self, R: np.ndarray) -> np.ndarray:
        """The resultant (3,) N of the residual's free components (a node may be held in
        some directions only: symmetry rollers)."""
        return np.where(self.free, R, 0.0).reshape(-1, 3).sum(axis=0)

    # -- Newton ---------------------------------------------------------------------------
    def matrix(self, s: NewtonState, ev, shift: float) -> sp.csr_matrix:
        """The system matrix (ANP: augmented) of the tissue evaluation ``ev`` at ``s`` with the
        contact Hessians, ``shift`` added to the free displacement diagonal, and identity
        rows/columns at the fixed dofs."""
        data = ev.data.copy()
        pat = self.p.pattern
        for e in s.plates:
            if e.hess is not None and e.hess.nnz:
                scatter_add(data, pat.dof_positions(e.hess.row, e.hess.col), e.hess.data)
        extra = None
        if s.skin is not None and s.skin.hess is not None:
            rows, cols, vals = s.skin.hess
            pos = pat.dof_positions(rows, cols)
            inside = pos >= 0
            scatter_add(data, pos[inside], vals[inside])
            extra = (rows[~inside], cols[~inside], vals[~inside])
        if shift > 0:
            data[self._diag] += shift
        M = system_matrix(self.p, ev, data)
        zero, diag = self._cons
        M.data[zero] = 0.0
        M.data[diag] = 1.0
        return self._with_couplings(M, extra)

    def _with_couplings(self, M: sp.csr_matrix, extra) -> sp.csr_matrix:
        """``M`` with the barrier's couplings outside the mesh's pattern added (between
        free dofs; a fixed dof keeps its identity row).  The extra pattern is the union of
        the node pairs coupled so far by this minimiser, zero where a pair is not in reach
        now, so that the linear solver's analysis is redone only when a new pair comes; the
        pattern is built once per union and the values scattered into it."""
        if extra is not None and len(extra[0]):
            r, c, v = extra
            keep = self.free[r] & self.free[c]
            r, c, v = r[keep], c[keep], v[keep]
            nodes = len(self.p.X)
            pairs = np.unique((r // 3) * nodes + c // 3)
            if self._pairs is not None:
                pairs = np.union1d(self._pairs, pairs)
            if self._pairs is None or len(pairs) != len(self._pairs):
                self._pairs, self._coupled = pairs, None
        else:
            r = c = np.zeros(0, np.int64)
            v = np.zeros(0)
        if self._pairs is None:
            return M
        M.sort_indices()  # row-major with sorted columns: M's entry keys are sorted
        if self._coupled is None or self._coupled[0] != M.nnz:
            self._coupled = self._coupled_pattern(M)
        _, indptr, indices, keys, base = self._coupled
        data = np.zeros(len(indices))
        data[base] = M.data
        if len(v):
            data += np.bincount(np.searchsorted(keys, r * M.shape[0] + c), weights=v,
                                minlength=len(data))
        out = sp.csr_matrix((data, indices, indptr), shape=M.shape, copy=False)
        out.has_sorted_indices = True
        return out

    def _coupled_pattern(self, M: sp.csr_matrix) -> tuple:
        """The pattern of ``M`` joined with a 3x3 block for every node pair of
        ``self._pairs`` (keys ``i * N + j``; ``M`` with sorted indices): ``(M.nnz, indptr,
        indices, keys, base)`` with the sorted entry keys ``row * n + col`` and the
        positions of ``M``'s entries."""
        n = M.shape[0]
        i, j = np.divmod(self._pairs, len(self.p.X))
        k = np.arange(3)
        pr = (3 * i[:, None, None] + k[None, :, None]).repeat(3, axis=2).reshape(-1)
        pc = (3 * j[:, None, None] + k[None, None, :]).repeat(3, axis=1).reshape(-1)
        mkeys = np.repeat(np.arange(n, dtype=np.int64) * n, np.diff(M.indptr)) + M.indices
        new = np.unique(pr * n + pc)
        at = np.minimum(np.searchsorted(mkeys, new), len(mkeys) - 1)
        new = new[mkeys[at] != new]
        base = np.arange(len(mkeys)) + np.searchsorted(new, mkeys)     # merge the two
        keys = np.empty(len(mkeys) + len(new), np.int64)
        keys[base] = mkeys
        keys[np.arange(len(new)) + np.searchsorted(mkeys, new)] = new
        rows, cols = np.divmod(keys, n)
        indptr = np.searchsorted(rows, np.arange(n + 1)).astype(np.int32)
        return (M.nnz, indptr, cols.astype(np.int32), keys, base)

    def reachable(self, u_from: np.ndarray, u_to: np.ndarray) -> bool:
        """Whether the straight path from ``u_from`` to ``u_to`` (N, 3) mm crosses no
        triangle of the outer surface (always, without a barrier)."""
        if self.barrier is None:
            return True
        return self.barrier.near(u_from, np.asarray(u_to) - np.asarray(u_from))[1] >= 1.0

    def direction(self, s: NewtonState) -> np.ndarray:
        """A descent direction ``du`` (3N,): the Newton correction of the consistent Hessian
        when its factorisation has the inertia of a positive definite condensed Hessian;
        otherwise of the Hessian whose tetrahedra are projected onto the positive
        semi-definite cone (:func:`.problem.evaluate`), which has it by construction, and
        only if that one is singular, shifted by ``tau`` times its mean free diagonal
        (``tau = 1e-6, 8e-6, ...``; Nocedal & Wright, algorithm 3.3).  A correction solved on
        an earlier factorisation (GMRES) must pass the angle test ``-R . du >= 1e-8 |R|
        |du|`` instead, or the matrix is factorised afresh."""
        n = self.p.n_dofs
        b = np.zeros(self.p.layout.n)
        b[:n] = -np.where(self.free, s.R, 0.0)
        dscale = float(np.mean(np.abs(s.ev.data[self._diag][self.free])))
        tau, refactor, ev = 0.0, False, s.ev
        for _ in range(12):
            t0 = time.perf_counter()
            M = self.matrix(s, ev, tau * dscale)
            nf = self.ls.n_factorisations
            try:
                x = self.ls.solve(M, b, refactor=refactor, rtol=FORCING)
            except LinearSolveError:
                x = None
            self.stats.t_solve += time.perf_counter() - t0
            fresh = self.ls.n_factorisations > nf
            self.stats.factorisations += int(fresh)
            self.stats.krylov_solves += int(not fresh)
            refactor = True
            if x is not None and np.all(np.isfinite(x)):
                inertia = self.ls.inertia() if fresh else None
                du = x[:n]
                slope = -float(s.R[self.free] @ du[self.free])
                definite = inertia is None or inertia[1] <= self.n_groups
                if definite and slope >= 1e-8 * np.linalg.norm(s.R[self.free]) * np.linalg.norm(du[self.free]):
                    return du
                if not definite:
                    self.stats.inertia_corrections += 1
                elif not fresh:  # an old factorisation's correction that does not descend
                    self.stats.rejected_directions += 1
                    continue
            if ev is s.ev:  # the consistent Hessian failed: project the tetrahedra
                t0 = time.perf_counter()
                ev = evaluate(self.p, s.u, want_k=True, project=True)
                self.stats.t_assembly += time.perf_counter() - t0
            else:
                tau = max(8.0 * tau, 1e-6)
        raise SolverDidNotConvergeError("no descent direction after 12 corrections of the Hessian "
                                        "(it is singular or not finite)")

    def line_search(self, s: NewtonState, du: np.ndarray, fext: np.ndarray,
                    plates: Sequence[PlatePotential]) -> NewtonState | None:
        """Backtracking (halving) on ``Pi`` from the full step, or from the self-contact
        barrier's step bound when that is shorter; None when no trial of 40 lowers it.

        A full step that lowers ``Pi`` by more than ``EXPAND_RATIO`` times what the
        quadratic model predicts (``-R . du / 2``) has met less curvature than the
        Hessian holds: the projection onto the positive semi-definite cone clamps the
        negative curvature of a path that snaps (a region slipping on a plate, the skin
        turning over a plate's edge), and full steps then creep along it by hundredths of a
        millimetre.  The step is doubled while ``Pi`` keeps falling (at most ``2^6``); the
        lowest trial is taken."""
        slope = float(s.R[self.free] @ du[self.free])
        scale = 1e-12 * (abs(s.energy) + float(np.abs(fext) @ np.abs(s.u.reshape(-1))) + 1e-12)
        a, pairs = 1.0, None
        if self.barrier is not None:  # the largest step that crosses no triangle
            t0 = time.perf_counter()
            pairs, a = self.barrier.near(s.u, du)
            if a < 1.0:
                self.stats.ccd_limited += 1
            log.log(5, "  barrier: %d pairs in reach of the step (largest move %.3g mm), step "
                    "bound %.3g, %.3f s", len(pairs), np.abs(du).max(), a, time.perf_counter() - t0)
        for k in range(40):
            self.stats.line_search_trials += 1
            trial = self.state(s.u + a * du.reshape(-1, 3), fext, plates, hessian=False,
                               pairs=pairs)
            if trial is not None and trial.energy <= s.energy + ARMIJO_C * a * slope + scale:
                self.full_step = a == 1.0
                if a == 1.0 and trial.energy - s.energy < EXPAND_RATIO * 0.5 * slope:
                    trial = self._expand(s, trial, du, fext, plates)
                return trial
            a *= 0.5
        return None

    def _expand(self, s: NewtonState, best: NewtonState, du: np.ndarray, fext: np.ndarray,
                plates: Sequence[PlatePotential]) -> NewtonState:
        """The lowest of ``Pi(u + 2^k du)``, k = 1..6, while it keeps falling (``best``: k = 0)."""
        a = 1.0
        for _ in range(6):
            a *= 2.0
            pairs = None
            if self.barrier is not None:
                pairs, safe = self.barrier.near(s.u, a * du)
                if safe < 1.0:
                    break
            self.stats.line_search_trials += 1
            trial = self.state(s.u + a * du.reshape(-1, 3), fext, plates, hessian=False,
                               pairs=pairs)
            if trial is None or trial.energy >= best.energy:
                break
            best = trial
        return best

    def solve(self, u: np.ndarray, fext: np.ndarray, plates: Sequence[PlatePotential], *,
              loose: float = 0.0, start: NewtonState | None = None,
              predictor: bool = False) -> NewtonState:
        """Minimise ``Pi`` from ``u`` (N, 3) at fixed loads and lags; raises
        :class:`SolverDidNotConvergeError` after ``max_iterations``.

        ``loose > 0``: stop as soon as the residual and its resultant are within ``loose``
        times their tolerances, without the correction test: the inexact inner
        minimisation of an augmented-Lagrangian iteration whose multipliers are about to
        be updated (Conn, Gould & Toint 1991; Nocedal & Wright section 17.4), whose state
        is never accepted as the increment's result.  ``start``: the state at ``u`` with
        its Hessian, when the caller has it at the same loads and lags (not evaluated
        again).  ``predictor`` (with ``loose``): the plates' lag is an increment's
        extrapolated start; stop also after the first Newton iteration when it took the
        whole Newton step (the start was in Newton's local region) and the residual norm is
        below the friction-force error of that lag (:meth:`lag_dominates`), which its update
        corrects (:func:`.minimise._increment`)."""
        s = start if start is not None else self.state(u, fext, plates, hessian=True)
        if s is None:
            raise SolverDidNotConvergeError("an element is inverted at the start of the increment")
        for it in range(self.max_iterations):
            if loose > 0 and self.converged(s, loose):
                return s
            if predictor and it == 1 and self.full_step and self.lag_dominates(s, plates):
                return s
            forces_ok = self.converged(s)
            du = self.direction(s)
            if forces_ok and np.abs(du[self.free]).max(initial=0.0) <= self.o.disp_abs_tol_mm:
                return s
            self.stats.iterations += 1
            trials = self.stats.line_search_trials
            nxt = self.line_search(s, du, fext, plates)
            if nxt is None:
                raise SolverDidNotConvergeError("line search found no decrease of the potential")
            if log.isEnabledFor(5):
                log.log(5, "  iteration: Pi %.10g -> %.10g, |R| %.3g -> %.3g N, |du| %.3g mm, "
                        "step 2^-%d, corrections %d", s.energy, nxt.energy,
                        np.linalg.norm(s.R[self.free]), np.linalg.norm(nxt.R[self.free]),
                        np.abs(nxt.u - s.u).max(), self.stats.line_search_trials - trials - 1,
                        self.stats.inertia_corrections)
            s = self.state(nxt.u, fext, plates, hessian=True)
            if s is None:  # cannot happen: the line search evaluated this state
                raise SolverDidNotConvergeError("inverted element at an accepted state")
            if self.on_iteration is not None:
                self.on_iteration()
        raise SolverDidNotConvergeError(
            f"no equilibrium in {self.max_iterations} Newton iterations (|R| = "
            f"{np.linalg.norm(s.R[self.free]):.3g} N, reference {s.f_ref:.3g} N; {self.where(s, plates)})")

    def lag_dominates(self, s: NewtonState, plates: Sequence[PlatePotential]) -> bool:
        """Whether the residual norm at ``s`` is below the plates' friction-force error
        (N; :meth:`.potential.PlatePotential.friction_force_error`, summed; False without
        friction)."""
        err = sum(pl.friction_force_error(e) for pl, e in zip(plates, s.plates))
        return err > 0 and float(np.linalg.norm(s.R[self.free])) <= err

    def where(self, s: NewtonState, plates: Sequence[PlatePotential]) -> str:
        """The node region of the largest residual: the node, its position (mm), its
        distance from the chest-wall plane and the nearest plate."""
        r = np.where(self.free, s.R, 0.0).reshape(-1, 3)
        i = int(np.argmax(np.linalg.norm(r, axis=1)))
        x = self.p.X[i] + s.u[i]
        text = (f"largest residual {np.linalg.norm(r[i]):.3g} N at node {i}, x = "
                f"({x[0]:.1f}, {x[1]:.1f}, {x[2]:.1f}) mm, {x[0] - self.p.X[:, 0].min():.1f} mm "
                "in front of the chest-wall plane")
        gaps = [(float(pl.c.plate.query(x[None]).gap[0]), pl.name) for pl in plates
                if pl.name != "chest-wall"]
        if gaps:
            g, name = min(gaps)
            text += f", {g:.1f} mm from the {name} plate"
        return text


def _linear_solver(problem: Problem, o) -> LinearSolver:
    """The problem's linear solver (the symbolic analysis of its fixed pattern is kept)."""
    ls = getattr(problem, "_minimiser_solver", None)
    if ls is None:
        ls = LinearSolver(o.linear_solver, dof_nodes=dof_nodes(problem), decoupled=problem.fixed_dofs)
        problem._minimiser_solver = ls  # type: ignore[attr-defined]
    return ls
