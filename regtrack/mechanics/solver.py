"""Quasi-static residual Newton-Raphson solver with line search and adaptive load stepping.

Kept for comparison (``[mechanics.solver] method = "newton"``); the default step solver
minimises the incremental potential (:mod:`.minimise`).

A step runs a pseudo-time ``t`` from 0 to 1 in increments.  Each increment solves

    R(u) = f_int(u) + sum_c r_c(u) - f_ext(t) = 0   on the free dofs,
    u = u_D(t)                                       on the constrained dofs,

(``f_int``: tissue + skin, :mod:`.problem`; ``r_c``: contributions such as contact,
:mod:`.contributions`; ``f_ext``: gravity; forces in N, displacements in mm) by Newton with
the consistent tangent.  Constrained rows/columns are replaced by the identity in the fixed
sparsity pattern, so the factorisation analysis is re-used; the prescribed increment
enters the first iteration's right-hand side (``-K_fc du_c``), the linear predictor.

Convergence (both, :class:`.config.SolverOptions`): ``||R_free|| <= force_tol * F_ref``
with ``F_ref = max(F_ext, ||reaction||, F_c, ||f_int|| / sqrt(ndof), force_floor)``
(``F_ext``: the larger of the L2 norm and the resultant of the external load; ``F_c``: the
largest resultant force of a contribution, i.e. the plate force.  Resultants, because the
L2 norm of nodal forces is smaller than the load carried by about the square root of the
number of loaded nodes), and ``||du||_inf <= max(disp_tol * max(||u - u_start||_inf,
disp_floor), disp_abs_tol)``, ``u_start`` the state at the increment's start.

Safeguards of an increment, each for a failure seen on frictional contact:

* chatter control: when the residual stops falling (``stagnation_ratio``), the
  contributions ``freeze()`` their stick/slip state for the rest of the solve and check it
  after convergence; a residual still falling tenfold per iteration gets up to
  ``extra_iterations`` more;
* stalled acceptance: an increment whose iterations run out accepts its best iterate when
  its residual is below ``stall_force_tol * F_ref`` (5e-3, Abaqus's default), because
  Newton wanders at a small residual on soft tangential modes of contact nodes, which a
  cut-back does not cure (counted in ``stalled_accepts``);
* line search (:meth:`_Newton.line_search`): ``du.R(u + a du) <= ratio |du.R(u)|``, or
  Armijo on ``|R|`` (``line_search_merit``); ``"auto"`` retries a failed increment with
  the other merit and then with the contributions' other tangent; elements may not invert;
* stabilisation (``stabilisation = "auto"``; Abaqus *STATIC, STABILIZE, the proximal-point
  method): a failed increment is solved again from ``u_n`` with the damping force ``c (u -
  u_n)``, ``c = alpha max(diag K(u_n), floor)``, i.e. it minimises the energy plus ``1/2
  |u - u_n|^2_c``, which stiffens the near-singular modes of tissue pinched between a plate
  and the fixed chest wall.  A damped state is never returned: an undamped "settle" solve
  at the same load follows (from the stabilised multipliers, ``settle_multipliers``), and a
  step whose last increment was damped ends with undamped solves at ``t = 1`` (``_polish``);
* predictor (``extrapolation = "linear"``): an increment starts from ``u_n + min(dt /
  dt_prev, 2) (u_n - u_n-1)`` when no element inverts there and its residual is below that
  of ``u_n``, because with ``u_n`` alone the skin under the advanced plate penetrates it by
  the whole travel of the increment;
* fresh factorisation at an increment's start (``increment_refactor = "adaptive"``): once
  an increment's first solve has failed on re-used factors, each later increment of the
  step factorises at its first iteration, because in a plate move the old factors fail
  there as a rule and the matrix change does not announce it.

An increment that fails (iterations exhausted, divergence, inversion, NaN) is rolled back
and cut (``cutback``); easy increments grow the next one (``growth``).  Below
``min_increment`` the step stops with :class:`SolverDidNotConvergeError`, which keeps the
last converged state and the load fraction reached.  A caller that can retry a step
another way (the protocol engine's plate moves) asks for the crawl guard (``crawl_guard``,
:func:`_crawling`: a step that keeps needing stabilisation in small increments) and the
stall guard (``stall_guard``: the last increment failing twice with a contribution's
multipliers stalled on the same node, :class:`_Stalled`); both stop the step with
:class:`SolverCrawlError`, since further cut-backs only shorten the way to the same state.
Measured figures of these choices: docs/performance-mechanics.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from regtrack.errors import ContactDidNotConvergeError, SolverCrawlError, SolverDidNotConvergeError
from regtrack.mechanics.config import SolverOptions
from regtrack.mechanics.contributions import Contribution
from regtrack.mechanics.linsolve import LinearSolveError, LinearSolver, serial_openblas
from regtrack.mechanics.problem import (Problem, body_force, build_problem, dof_nodes, evaluate,
                                        internal_force, scatter_add, system_matrix, tangent)
from regtrack.mechanics.types import StepStats

__all__ = ["Problem", "build_problem", "internal_force", "tangent", "solve_step", "reaction_forces"]

log = logging.getLogger(__name__)

Gravity = Callable[[float], np.ndarray]
Dirichlet = Callable[[float], tuple[np.ndarray, np.ndarray]]
Progress = Callable[[str, float], None]


_EXTRAPOLATION_MAX = 2.0  # largest ratio dt / dt_prev of the linear predictor


class _Failed(Exception):
    """An increment did not converge (internal; triggers a cut-back)."""


class _Stalled(_Failed):
    """The augmented-Lagrangian multipliers of a contribution stalled (internal);
    ``where`` identifies the stalled node (e.g. ``(plate, skin node)``)."""

    def __init__(self, message: str, where: Any):
        super().__init__(message)
        self.where = where


class _Constraints:
    """Constrained dofs and the system-matrix value positions that identity rows replace."""

    def __init__(self, problem: Problem, dofs: np.ndarray):
        lay = problem.layout
        self.dofs = dofs
        mask = np.zeros(problem.n_dofs, bool)
        mask[dofs] = True
        self.mask = mask
        self.free = ~mask
        smask = np.zeros(lay.n, bool)
        smask[dofs] = True
        self.system_mask = smask
        rows = np.repeat(smask, np.diff(lay.indptr))
        self.zero = rows | smask[lay.indices]
        diag = problem.pattern.dof_positions(dofs, dofs)
        self.diag = diag if lay.k_pos is None else lay.k_pos[diag]

    def apply(self, M: sp.csr_matrix) -> sp.csr_matrix:
        """Replace, in place, the constrained rows and columns of a system matrix of the
        fixed layout by the identity; returns ``M``."""
        M.data[self.zero] = 0.0
        M.data[self.diag] = 1.0
        return M


def _constraint_targets(problem: Problem, u_start: np.ndarray, dirichlet: Dirichlet | None, t: float):
    dofs = problem.fixed_dofs
    vals = u_start[dofs]
    if dirichlet is not None:
        d, v = dirichlet(t)
        d = np.asarray(d, np.int64).reshape(-1)
        v = np.broadcast_to(np.asarray(v, float).reshape(-1), d.shape)
        keep = ~np.isin(dofs, d)
        dofs = np.concatenate([dofs[keep], d])
        vals = np.concatenate([vals[keep], v])
        order = np.argsort(dofs)
        dofs, vals = dofs[order], vals[order]
    return dofs, vals


def _constrained(assemble: Callable[[], sp.csr_matrix], cons: _Constraints):
    """``assemble`` followed by :meth:`_Constraints.apply` (not called until needed)."""
    return lambda: cons.apply(assemble())


class _Newton:
    """State of one step's Newton solves (problem, loads, contributions, statistics)."""

    def __init__(self, problem, contributions, options, stats, linsolver):
        self.p = problem
        self.contribs = list(contributions)
        self.o = options
        self.stats = stats
        self.ls = linsolver
        self._cons_cache: dict[bytes, _Constraints] = {}
        self.first_solve_iterations = 0
        self.damping: tuple[np.ndarray, np.ndarray] | None = None  # (c per dof (N/mm), u_start)
        self._diag: np.ndarray | None = None
        self.damped_last = False  # the last accepted increment stayed damped (settle failed)
        self.stabilised_last = False  # the last increment needed stabilisation (settled or not)
        self.guess: np.ndarray | None = None  # starting guess of the next undamped solve
        self.increment_start = False  # the next linear solve is an increment's first (_increment)
        self.refactor_starts = False  # increment_refactor = "adaptive": a first re-use failed

    def start(self, u: np.ndarray, guess: np.ndarray, fext: np.ndarray, cons: _Constraints) -> np.ndarray:
        """The start of an increment's Newton iterations: the extrapolated ``guess`` if no
        element inverts there and its free-dof residual is below that of ``u``, else ``u``
        (two residual evaluations; figures in the module docstring).  Also trying the point
        halfway to the guess (where the guess inverts elements at the plate edge) gave
        more iterations in total (phantom CC / MLO 344 / 65, exam 03 295 / 86): the paths of
        these frictional, pinched problems are chaotic, so only totals over several models
        decide such choices."""
        R0, _, _ = self.residual(u, fext, want_k=False)
        R1, _, _ = self.residual(guess, fext, want_k=False)
        if R1 is None or (R0 is not None and np.linalg.norm(R1[cons.free]) >= np.linalg.norm(R0[cons.free])):
            return u
        self.stats.extrapolated_increments += 1
        return guess

    def stabilise(self, u_start: np.ndarray | None, scale: float = 1.0) -> None:
        """Proximal stabilisation about ``u_start`` (None: off).  Adds the force
        ``c (u - u_start)`` to the residual and ``diag(c)`` to the tangent, with
        ``c = alpha max(diag K(u_start), floor)`` (tissue and skin tangent; ``floor``: 1 %
        of the median positive diagonal; ``alpha = scale * stabilisation_factor``), i.e. each
        solve minimises ``Pi(u) + 1/2 (u - u_start)^T diag(c) (u - u_start)``."""
        if u_start is None:
            self.damping = None
            return
        if self._diag is None:
            self._diag = self.p.pattern.diagonal_positions()
        ev = evaluate(self.p, u_start, want_k=True)
        kd = ev.data[self._diag]
        pos = kd[kd > 0]
        floor = 0.01 * float(np.median(pos)) if len(pos) else 1e-9
        self.damping = (scale * self.o.stabilisation_factor * np.maximum(kd, floor), u_start.copy())

    def constraints(self, dofs: np.ndarray) -> _Constraints:
        key = dofs.tobytes()
        if key not in self._cons_cache:
            self._cons_cache = {key: _Constraints(self.p, dofs)}
        return self._cons_cache[key]

    def residual(self, u: np.ndarray, fext: np.ndarray, want_k: bool):
        t0 = time.perf_counter()
        ev = evaluate(self.p, u, want_k=want_k)
        self.stats.t_assembly += time.perf_counter() - t0
        if ev.n_inverted != 0 or not np.all(np.isfinite(ev.f)):
            return None, None, None
        R = ev.f - fext
        if self.damping is not None:
            R = R + self.damping[0] * (u - self.damping[1])
        ktan = []
        t0 = time.perf_counter()
        fc2 = 0.0
        for c in self.contribs:
            rc, kc = c.residual_tangent(u.reshape(-1, 3))
            rc = np.asarray(rc, float).reshape(-1)
            fc2 = max(fc2, float(np.linalg.norm(rc.reshape(-1, 3).sum(axis=0))))
            R = R + rc
            if kc is not None and want_k:
                pre = getattr(c, "preconditioner_tangent", None)
                ktan.append((kc, None if pre is None else pre()))
        self.stats.t_contrib += time.perf_counter() - t0
        ev.contrib_norm = fc2  # largest resultant contact (plate) force, part of the force reference
        return R, ev, ktan

    def matrix(self, ev, ktan: list):
        """System matrix with contributions, before the constraint rows are replaced, and
        the matrix to precondition it with (None: the solver's default, the symmetric part),
        as a function that assembles it: the linear solver needs it only when it
        factorises, about one Newton iteration in three (its system matrix cost ~7 ms per
        iteration on the 9.5k-node benchmark hemisphere).

        ``ktan``: (tangent, preconditioner tangent or None) per contribution (see
        :mod:`.contributions`, ``preconditioner_tangent``).  The preconditioning matrix is
        the same sum with each contribution's preconditioner tangent in place of its
        tangent; it shares the system matrix's layout (None if a tangent falls outside
        the pattern or no contribution offers one)."""
        pat = self.p.pattern
        data = ev.data
        if self.damping is not None:
            data[self._diag] += self.damping[0]
        n = self.p.layout.n
        extra = []
        self.symmetric = True
        pdata = None
        if self.o.preconditioner == "fixed-bound" and any(kp is not None for _, kp in ktan):
            pdata = data.copy()
        for kc, kp in ktan:
            kc = sp.coo_matrix(kc)
            asym = abs(kc - kc.T)
            if asym.nnz and asym.max() > 1e-12 * abs(kc).max():
                self.symmetric = False
            pos = pat.dof_positions(kc.row, kc.col)
            if np.all(pos >= 0):
                scatter_add(data, pos, kc.data.astype(float))
                if pdata is not None:
                    kp = kc if kp is None else sp.coo_matrix(kp)
                    ppos = pos if kp is kc else pat.dof_positions(kp.row, kp.col)
                    if np.all(ppos >= 0):
                        scatter_add(pdata, ppos, kp.data.astype(float))
                    else:
                        pdata = None
            else:
                extra.append(sp.coo_matrix((kc.data, (kc.row, kc.col)), shape=(n, n)))
        K = system_matrix(self.p, ev, data)
        for kc in extra:  # outside the pattern: generic sum (new analysis)
            log.debug("contribution tangent outside the pattern: generic assembly")
            K = (K + kc).tocsr()
        if extra or pdata is None or self.symmetric:
            return K, not extra, None
        return K, True, lambda: system_matrix(self.p, ev, pdata)

    def solve_increment(self, u_start: np.ndarray, fext: np.ndarray, dofs: np.ndarray, vals: np.ndarray,
                        hist: list[float], u_base: np.ndarray | None = None,
                        loose_tol: float | None = None) -> np.ndarray:
        """Newton solve from ``u_start``; ``u_base`` (default ``u_start``) is the state at the
        start of the increment, the reference of the displacement test (a re-solve after a
        multiplier update starts from the converged state, but its corrections are judged
        against the whole increment's motion, not against the re-solve's own).

        ``loose_tol``: an inexact solve (``augmentation_force_tol``), done after at least one
        Newton iteration once ``|R| <= loose_tol F_ref`` with the constraints met (no
        displacement test)."""
        o = self.o
        cons = self.constraints(dofs)
        u = u_start.copy()
        base = u_start if u_base is None else u_base
        first_solve, self.increment_start = self.increment_start, False
        n_hist0 = len(hist)
        frozen = False
        # |f_ext|: the larger of the L2 norm and the resultant (the weight, for gravity)
        fnorm_ext = max(float(np.linalg.norm(fext)),
                        float(np.linalg.norm(fext.reshape(-1, 3).sum(axis=0))))
        du_prev = np.inf

        best = (np.inf, None)  # (residual / F_ref, iterate) of the best iterate meeting the constraints

        def check(R, ev, u, du_last):
            """(residual norm, converged?) of the state u reached by the correction du_last."""
            nonlocal best
            ducon = np.zeros_like(u)
            ducon[dofs] = vals - u[dofs]
            f_ref = max(fnorm_ext, float(np.linalg.norm(R[cons.mask])), ev.contrib_norm,
                        float(np.linalg.norm(ev.f)) / np.sqrt(len(u)), o.force_floor_n)
            rn = float(np.linalg.norm(R[cons.free]))
            u_ref = max(float(np.max(np.abs(u - base), initial=0.0)), o.disp_floor_mm)
            cons_ok = not np.any(ducon) or float(np.max(np.abs(ducon))) <= o.disp_tol * u_ref
            du_ok = du_last <= o.disp_tol * u_ref or du_last <= o.disp_abs_tol_mm
            if cons_ok and rn < best[0] * f_ref:
                best = (rn / f_ref, u)
            if loose_tol is not None:
                return rn, ducon, (rn <= loose_tol * f_ref and cons_ok and len(hist) > n_hist0)
            return rn, ducon, (rn <= o.force_tol * f_ref and cons_ok and du_ok)

        limit = o.max_iterations
        it = -1
        while True:
            it += 1
            R, ev, ktan = self.residual(u, fext, want_k=True)
            if R is None:
                raise _Failed("inverted elements or non-finite forces")
            rn, ducon, ok = check(R, ev, u, 0.0 if it == 0 else du_prev)
            hist.append(rn)
            if ok:
                return u
            rs = hist[n_hist0:]
            if it >= limit:
                # still converging fast (each of the last two residuals below a tenth of the one
                # before): a few more iterations finish it, cheaper than a cut-back
                if (limit < o.max_iterations + o.extra_iterations and len(rs) >= 3
                        and rs[-1] < 0.1 * rs[-2] and rs[-2] < 0.1 * rs[-3]):
                    limit += 1
                    self.stats.extra_iterations += 1
                else:
                    break
            if (it >= 5 and best[0] <= o.stall_force_tol
                    and min(rs[-3:]) > o.stagnation_ratio * rs[-4]):
                break  # stalled below the stall tolerance: accept the best iterate now
            if not frozen and it >= 3 and rn > o.stagnation_ratio * min(rs[-4:-1]):
                # no progress over the last iterations: contact-state chatter (stick/slip
                # switching); freeze the contributions' state for the rest of this solve
                frozen = True
                for c in self.contribs:
                    if hasattr(c, "freeze"):
                        c.freeze()
                self.stats.freezes += 1
            if it > 2 and rn > 1e8 * max(hist[0], o.force_floor_n):
                raise _Failed("residual diverged")
            self.stats.iterations += 1
            K, fixed_layout, P = self.matrix(ev, ktan)
            n3, n = len(u), K.shape[0]
            rhs = np.zeros(n)
            rhs[:n3] = -R
            if np.any(ducon):
                rhs -= K @ np.concatenate([ducon, np.zeros(n - n3)])
            rhs[:n3][cons.mask] = ducon[cons.mask]
            if fixed_layout:
                cons.apply(K)
                if P is not None:  # assembled by the linear solver only if it factorises
                    P = _constrained(P, cons)
            else:
                keep = (~cons.system_mask).astype(float)
                K = (sp.diags(keep) @ K @ sp.diags(keep) + sp.diags(1.0 - keep)).tocsr()
            t0 = time.perf_counter()
            refactor = first_solve and it == 0 and (
                o.increment_refactor == "always"
                or (o.increment_refactor == "adaptive" and self.refactor_starts))
            failures = self.ls.n_reuse_failures
            try:
                du = self.ls.solve(K, rhs, symmetric=self.symmetric, rtol=self.forcing(hist),
                                   preconditioner=P, refactor=refactor)[:n3]
            except LinearSolveError as exc:
                raise _Failed(str(exc)) from None
            if refactor:
                self.stats.increment_refactors += 1
            elif first_solve and it == 0 and self.ls.n_reuse_failures > failures:
                self.refactor_starts = True  # the re-used factors fail at increment starts
            self.stats.t_solve += time.perf_counter() - t0
            if not np.all(np.isfinite(du)):
                raise _Failed("linear solve returned non-finite values")
            alpha, R1, ev1 = self.line_search(u, du, R, fext, cons)
            u = u + alpha * du
            du_prev = float(np.max(np.abs(alpha * du)))
            if R1 is not None:  # the line search already has R at the new state: skip a tangent
                rn1, _, ok1 = check(R1, ev1, u, du_prev)
                if ok1:
                    hist.append(rn1)
                    return u
        if best[1] is not None and best[0] <= o.stall_force_tol:
            # Newton wanders at a small residual (soft tangential modes of contact nodes):
            # accept the best iterate rather than cut back; counted and reported
            self.stats.stalled_accepts += 1
            self.stats.stalled_residual_max = max(self.stats.stalled_residual_max, best[0])
            log.debug("increment accepted at its best iterate: |R| / F_ref = %.2e", best[0])
            return best[1]
        raise _Failed(f"no convergence in {limit} iterations (|R| = {hist[-1]:.3g} N)")

    def forcing(self, hist: list[float]) -> float | None:
        """Relative tolerance of the linear solve (inexact Newton, Eisenstat & Walker 1996,
        choice 2): ``eta_k = min(forcing_max, 0.9 (|R_k| / |R_k-1|)^2)``, ``forcing_max`` at
        an increment's first iteration; None (direct solve) without factorisation re-use."""
        o = self.o
        if not o.reuse_factorisation:
            return None
        if len(hist) < 2 or hist[-2] <= 0:
            return o.forcing_max
        return min(o.forcing_max, 0.9 * (hist[-1] / hist[-2]) ** 2)

    def line_search(self, u, du, R, fext, cons):
        """Step length in (0, 1] with the residual and evaluation at the accepted point (None
        if not evaluated).  Inverted elements halve the step.

        ``line_search_merit = "residual"``: Armijo backtracking on the merit function
        ``phi(a) = |R_free(u + a du)|^2 / 2``.  For the Newton direction ``K du = -R``,
        ``phi'(0) = -|R|^2`` whatever the definiteness or symmetry of ``K``, so the test
        ``|R(a)| <= (1 - 1e-4 a) |R(0)|`` is always satisfiable for small ``a``; a failed
        trial takes the minimiser of the quadratic through ``phi(0), phi'(0), phi(a)``,
        kept in ``[0.1, 0.5] a``.  After ``line_search_max`` trials the trial with the
        smallest residual is taken.  (Measured on the phantom CC compression: the
        tangent turns indefinite away from equilibrium, a third of the Newton directions
        ascend the energy, and the directional test accepted full steps that raised
        ``|R|`` a hundredfold.  Neither test is the more robust: on that run, with the
        same stall rule, the residual merit stopped at t = 0.998 where the directional test
        completed, and on Pelicano exam 03 CC (1,667 nodes) the reverse, directional
        stopping at t = 0.9976.  The default ``"auto"`` therefore tries the directional
        test and retries a failed increment once with the residual merit before cutting
        it back.)

        ``"directional"``: accept when ``du.R(u + a du) <= ratio |du.R(u)|`` (secant update
        bounded to ``[0.1, 1] a``); only for descent directions (``du.R(u) < 0``).
        """
        o = self.o
        free = cons.free
        residual = o.line_search_merit == "residual"  # "auto": directional, see solve_step
        s0 = float(du[free] @ R[free])
        r0 = float(np.linalg.norm(R[free]))
        search = o.line_search and (residual or s0 < 0)
        alpha = 1.0
        best = (np.inf, 1.0, None, None)
        t0 = time.perf_counter()
        try:
            for trial in range(o.line_search_max + 4):
                R1, ev1, _ = self.residual(u + alpha * du, fext, want_k=False)
                self.stats.line_search_trials += 1
                if R1 is None:  # an element inverts at this step length
                    self.stats.inverted_trials += 1
                    alpha *= 0.5
                    continue
                if not search:
                    return alpha, R1, ev1
                if residual:
                    r1 = float(np.linalg.norm(R1[free]))
                    if r1 <= (1.0 - 1e-4 * alpha) * r0:
                        return alpha, R1, ev1
                    if r1 < best[0]:
                        best = (r1, alpha, R1, ev1)
                    if trial >= o.line_search_max - 1:
                        return best[1], best[2], best[3]
                    phi0, phi1 = 0.5 * r0 * r0, 0.5 * r1 * r1
                    den = 2.0 * (phi1 - phi0 + 2.0 * phi0 * alpha)
                    a_q = 2.0 * phi0 * alpha * alpha / den if den > 0 else 0.5 * alpha
                    alpha = float(np.clip(a_q, 0.1 * alpha, 0.5 * alpha))
                    continue
                s1 = float(du[free] @ R1[free])
                if s1 <= o.line_search_ratio * abs(s0):
                    return alpha, R1, ev1
                if trial >= o.line_search_max - 1:
                    return alpha, None, None
                alpha *= float(np.clip(s0 / (s0 - s1), 0.1, 1.0))
            raise _Failed("line search could not avoid inverted elements")
        finally:
            self.stats.t_line_search += time.perf_counter() - t0


@serial_openblas()
def solve_step(problem: Problem, u0: np.ndarray, *, gravity: Gravity | None = None,
               dirichlet: Dirichlet | None = None, contributions: Sequence[Contribution] = (),
               options: SolverOptions | None = None, progress: Progress | None = None,
               step_name: str = "", step: Any = None,
               linear_solver: LinearSolver | None = None,
               crawl_guard: bool = False,
               stall_guard: bool = False) -> tuple[np.ndarray, StepStats]:
    """Solve one load step from ``u0`` (N, 3) mm over pseudo-time t in (0, 1].

    Parameters
    ----------
    gravity : callable t -> (3,) acceleration in m/s^2 (model frame); body force
        ``rho * g`` per reference volume (``rho`` in kg/m^3 -> N/mm^3 via 1e-9).
    dirichlet : callable t -> (dofs, values): prescribed displacements (mm) in addition
        to the model's fixed (chest-wall) nodes, which keep their ``u0`` values.
    contributions : extra residual/tangent terms (contact); call order documented in
        :mod:`regtrack.mechanics.contributions`.
    options : solver options (default: ``problem.config.solver``).
    progress : callable ``(step_name, t)`` after every converged increment.
    step : object handed to ``Contribution.begin_step``.
    crawl_guard : stop with :class:`SolverCrawlError` when the step crawls (see
        :func:`_crawling`; only for callers that retry the step differently).
    stall_guard : stop with :class:`SolverCrawlError` when the last increment (to t = 1)
        fails twice in a row with its contact multipliers stalled on the same node: the
        cut-backs in between only shorten the way to the same state at t = 1 (only for
        callers that retry the step differently; see the module docstring).

    Returns
    -------
    (u, stats) : displacement (N, 3) mm at t = 1 and :class:`StepStats`.

    Raises
    ------
    SolverDidNotConvergeError
        with ``load_fraction`` (last converged t) and ``last_converged`` (N, 3);
        :class:`SolverCrawlError` (a subclass) with ``crawl_guard``.

    numpy's OpenBLAS runs on one thread during the step, so the Newton path does not
    depend on the core count (:func:`regtrack.mechanics.linsolve.serial_openblas`).
    """
    o = options or problem.config.solver
    stats = StepStats(name=step_name)
    tstart, cstart = time.perf_counter(), time.process_time()
    ls = linear_solver or _linear_solver(problem, o)
    nfac0, nkry0, nan0, nkit0 = ls.n_factorisations, ls.n_krylov_solves, ls.n_analyses, ls.krylov_iterations
    nfail0, nwaste0 = ls.n_reuse_failures, ls.krylov_wasted_iterations
    newton = _Newton(problem, contributions, o, stats, ls)
    u = np.asarray(u0, float).reshape(-1).copy()
    for c in newton.contribs:
        c.begin_step(step)
    t, dt = 0.0, o.initial_increment
    u_eq, t_eq = u.copy(), 0.0  # last state that is an undamped equilibrium
    newton.damped_last = False
    prev: tuple[np.ndarray, float] | None = None  # (u, dt) at the start of the last accepted increment
    run: list[float] = []  # sizes of the current run of increments that needed stabilisation
    t1_stall = None  # the stalled node of the last failed increment to t = 1 (stall_guard)
    while t < 1.0 - 1e-12:
        dt = min(dt, 1.0 - t)
        if 1.0 - (t + dt) < 1e-9:
            dt = 1.0 - t
        t_new = t + dt
        hist: list[float] = []
        if o.extrapolation == "linear" and prev is not None:
            # linear predictor from the last two equilibria (growth capped at 2x)
            newton.guess = u + min(dt / prev[1], _EXTRAPOLATION_MAX) * (u - prev[0])
        try:
            u_new = _increment_with_retries(newton, u, t_new, gravity, dirichlet, hist, o, stats,
                                            skip_undamped=_skip_undamped(run, o))
        except _Failed as why:
            for c in newton.contribs:
                c.rollback()
            if t_new >= 1.0 - 1e-12:
                where = why.where if isinstance(why, _Stalled) else None
                if stall_guard and where is not None and where == t1_stall:
                    stats.t_total = time.perf_counter() - tstart
                    raise SolverCrawlError(
                        f"step '{step_name}': the last increment (to t = 1) failed twice with "
                        f"the contact multipliers stalled ({why}), the second time after a "
                        f"cut-back to t = {t:.4g}; cutting back further only shortens the "
                        f"way to the same state; stopped, keeping the last undamped "
                        f"equilibrium, at t = {t_eq:.4g}", load_fraction=t_eq,
                        last_converged=u_eq.reshape(-1, 3).copy()) from None
                t1_stall = where
            stats.cutbacks += 1
            log.info("%s: increment t = %.4g -> %.4g failed (%s); cutting back", step_name, t, t_new, why)
            dt *= o.cutback
            if dt < o.min_increment:
                stats.t_total = time.perf_counter() - tstart
                err = ContactDidNotConvergeError if "augment" in str(why) else SolverDidNotConvergeError
                raise err(f"step '{step_name}': Newton did not converge beyond load fraction t = {t_eq:.4g} "
                          f"({why}); try smaller [mechanics.solver] min_increment/initial_increment, more "
                          "max_iterations, or check the boundary conditions and loads",
                          load_fraction=t_eq, last_converged=u_eq.reshape(-1, 3).copy()) from None
            continue
        prev = (u, dt) if not newton.damped_last else None  # no predictor from a damped state
        run = run + [t_new - t] if newton.stabilised_last else []
        stats.stabilised_accepted += int(newton.stabilised_last)
        stats.longest_stabilised_run = max(stats.longest_stabilised_run, len(run))
        u, t = u_new, t_new
        if not newton.damped_last:
            u_eq, t_eq = u, t
        stats.increments += 1
        stats.residual_history.append(hist)
        for c in newton.contribs:
            c.commit(u.reshape(-1, 3))
        if newton.contribs:
            stats.reports.append({"t": t, **{c.name: c.report(u.reshape(-1, 3)) for c in newton.contribs}})
        if newton.first_solve_iterations <= o.easy_iterations:  # augmentation re-solves not counted
            dt = min(dt * o.growth, o.max_increment)
        if progress is not None:
            progress(step_name, t)
        if crawl_guard and _crawling(run, t, o):
            stats.t_total = time.perf_counter() - tstart
            size = float(np.mean(run[-o.crawl_increments:]))
            raise SolverCrawlError(
                f"step '{step_name}' crawls at t = {t:.4g}: the last {len(run)} increments each "
                f"needed stabilisation, the last {o.crawl_increments} of them {size:.3g} of the "
                f"step on average, and the rest (1 - t = {1 - t:.3g}) would take about "
                f"{(1 - t) / size:.0f} more; stopped, keeping the last undamped equilibrium, at "
                f"t = {t_eq:.4g} ([mechanics.solver] crawl_increments = 0 lets it crawl on)",
                load_fraction=t_eq, last_converged=u_eq.reshape(-1, 3).copy())
    if newton.damped_last:
        try:
            u = _polish(newton, u, gravity, dirichlet, o, stats)
        except _Failed as why:
            for c in newton.contribs:
                c.rollback()
            stats.t_total = time.perf_counter() - tstart
            raise SolverDidNotConvergeError(
                f"step '{step_name}': the stabilised solution at t = 1 did not reach an undamped "
                f"equilibrium ({why}); the last equilibrium is at load fraction t = {t_eq:.4g}; try a "
                "smaller [mechanics.solver] stabilisation_factor, more stabilisation_polish, or check "
                "the boundary conditions and loads",
                load_fraction=t_eq, last_converged=u_eq.reshape(-1, 3).copy()) from None
        if newton.contribs:  # the reports describe the returned (undamped) state
            stats.reports[-1] = {"t": t, **{c.name: c.report(u.reshape(-1, 3)) for c in newton.contribs}}
    stats.t_total = time.perf_counter() - tstart
    stats.cpu_total = time.process_time() - cstart
    stats.factorisations = ls.n_factorisations - nfac0
    stats.krylov_iterations = ls.krylov_iterations - nkit0
    stats.krylov_solves = ls.n_krylov_solves - nkry0
    stats.reuse_failures = ls.n_reuse_failures - nfail0
    stats.krylov_wasted_iterations = ls.krylov_wasted_iterations - nwaste0
    stats.analyses = ls.n_analyses - nan0
    log.debug("%s: %d increments, %d iterations, %d cut-backs, %.2f s", step_name, stats.increments,
              stats.iterations, stats.cutbacks, stats.t_total)
    return u.reshape(-1, 3), stats


def _crawling(run: list[float], t: float, o: SolverOptions) -> bool:
    """Crawl test: the last ``crawl_increments`` accepted increments (sizes ``run``, the
    current run of consecutive ones that needed stabilisation) all did, and the rest of the
    step, ``1 - t``, would take more than ``crawl_remaining`` increments of their mean size.
    Then the frictional path is stuck in the chest-wall pinch, and a retry on another path
    (smaller plate travel per increment) costs less than crawling on (a real MLO that
    crawled had about 130 increments left, one that finished about 24)."""
    n = o.crawl_increments
    return (n > 0 and len(run) >= n and t < 1.0 - 1e-12
            and (1.0 - t) > o.crawl_remaining * float(np.mean(run[-n:])))


def _skip_undamped(run: list[float], o: SolverOptions) -> bool:
    """Whether the next increment goes straight to the stabilised solve: the current run of
    consecutive stabilised increments (``run``) has at least ``stabilised_first_after`` of
    them, so the undamped attempt failed in each, and this is not a probe (every
    ``stabilised_probe``-th increment from there tries undamped first, to find the run's
    end).  A skipped attempt is one that would most likely fail after its full Newton
    budget; the stabilised retry that follows such a failure starts from the same state
    (no extrapolated guess, the contributions rolled back), so where the attempt would
    have failed the path is the same but for the linear solver's factorisation re-use.
    On the real MLOs that need stabilisation in every increment this saves about 15 % of
    the Newton iterations, plate forces within 1 % (docs/performance-mechanics.md).  A
    failed settle returns to the stabilised solve's state, so the increments that skip
    their attempt skip their settle too (``stabilised_skip_settle``)."""
    n = o.stabilised_first_after
    if n <= 0 or o.stabilisation != "auto" or len(run) < n:
        return False
    return (len(run) - n + 1) % o.stabilised_probe != 0


def _linear_solver(problem: Problem, o: SolverOptions) -> LinearSolver:
    """The problem's cached solver (the analysis of its fixed pattern is re-used across steps)."""
    key = (o.linear_solver, o.reuse_factorisation, o.precision, o.krylov_rtol, o.krylov_max,
           o.reuse_budget, o.ordering)
    cached = getattr(problem, "_linear_solver", None)
    if cached is None or cached[0] != key:
        cached = (key, LinearSolver(o.linear_solver, reuse_factorisation=o.reuse_factorisation,
                                    precision=o.precision, krylov_rtol=o.krylov_rtol, krylov_max=o.krylov_max,
                                    reuse_budget=o.reuse_budget,
                                    ordering=o.ordering, dof_nodes=dof_nodes(problem),
                                    decoupled=problem.fixed_dofs))
        problem._linear_solver = cached  # type: ignore[attr-defined]
    return cached[1]


def _increment_with_retries(newton: _Newton, u, t_new, gravity, dirichlet, hist, o: SolverOptions,
                            stats: StepStats, skip_undamped: bool = False) -> np.ndarray:
    """One increment; before the caller cuts back, a failed increment is solved again
    (from the same start) with, in turn: the residual (Armijo) line search
    (``line_search_merit = "auto"``, ``merit_retries``), then the contributions' other
    tangent (``swap_tangent``, ``tangent_retries``).  With ``stabilisation = "auto"`` the
    only retry is the stabilised one (:meth:`_Newton.stabilise`), which sets
    ``newton.damped_last``.  ``skip_undamped`` (:func:`_skip_undamped`): the stabilised
    solve at once, from ``u`` without the extrapolated guess, as after a failed attempt
    (its settle is still tried).  Raises the last ``_Failed``."""
    newton.damped_last = newton.stabilised_last = False
    if skip_undamped:
        newton.guess = None
        stats.skipped_undamped += 1
        why = _Failed("undamped attempt skipped in a stabilised run")
    else:
        it0 = stats.iterations
        try:
            return _increment(newton, u, t_new, gravity, dirichlet, hist)
        except _Failed as first:
            why = first
            stats.failed_undamped_iterations += stats.iterations - it0
    if o.stabilisation == "auto":
        for c in newton.contribs:
            c.rollback()
        stats.stabilised_increments += 1
        try:
            u_new = _stabilised_increment(newton, u, t_new, gravity, dirichlet, hist)
        except _Failed as again:
            log.info("%s: increment to t = %.4g failed undamped (%s) and stabilised (%s)",
                     stats.name, t_new, why, again)
            raise
        log.info("%s: increment to t = %.4g stabilised (undamped: %s)", stats.name, t_new, why)
        newton.stabilised_last = True
        if skip_undamped and o.stabilised_skip_settle:  # as if the settle had failed
            stats.skipped_settles += 1
            newton.damped_last = True
            return u_new
        # settle: undamped Newton at the same load from the stabilised state, so that the
        # damping lag does not carry into the next increment (which would then fail too)
        held = _trial_states(newton)
        it0 = stats.iterations
        try:
            u_set = _increment(newton, u_new, t_new, gravity, dirichlet, hist,
                               multipliers=held if o.settle_multipliers == "stabilised" else ())
        except _Failed:
            stats.failed_undamped_iterations += stats.iterations - it0
            for c, state in held:  # the commit stores the stabilised solve's state
                c.set_trial_state(state)
            newton.damped_last = True
            return u_new
        stats.settled_increments += 1
        return u_set
    if o.line_search_merit == "auto":
        for c in newton.contribs:
            c.rollback()
        stats.merit_retries += 1
        newton.o = replace(o, line_search_merit="residual")
        try:
            return _increment(newton, u, t_new, gravity, dirichlet, hist)
        except _Failed as again:
            why = again
        finally:
            newton.o = o
    swapped = [c for c in newton.contribs if getattr(c, "swap_tangent", None) is not None and c.swap_tangent()]
    if not swapped:
        raise why
    try:
        for c in newton.contribs:
            c.rollback()
        stats.tangent_retries += 1
        return _increment(newton, u, t_new, gravity, dirichlet, hist)
    finally:
        for c in swapped:
            c.swap_tangent()


def _trial_states(newton: _Newton) -> list[tuple[Any, Any]]:
    """(contribution, :meth:`trial_state`) of the contributions that have one."""
    return [(c, c.trial_state()) for c in newton.contribs
            if getattr(c, "trial_state", None) is not None]


def _stabilised_increment(newton: _Newton, u: np.ndarray, t: float, gravity, dirichlet, hist,
                          scale: float = 1.0) -> np.ndarray:
    """:func:`_increment` with proximal stabilisation about ``u`` (``scale`` times the
    configured weight); the damping is removed whatever the outcome."""
    newton.stabilise(u, scale)
    try:
        return _increment(newton, u, t, gravity, dirichlet, hist)
    finally:
        newton.stabilise(None)


def _polish(newton: _Newton, u: np.ndarray, gravity, dirichlet, o: SolverOptions, stats: StepStats) -> np.ndarray:
    """Undamped equilibrium at t = 1 from a stabilised state: an undamped solve, and while
    that fails, one more stabilised (proximal) solve about the current state; at most
    ``stabilisation_polish`` rounds; a proximal solve that fails is not taken, and the next
    round damps 4x harder; one that converges is taken, and the next round damps 2x less
    (down to 1/64 of the first: the proximal step grows while it succeeds, so a state that
    creeps towards a distant equilibrium by the same small step every round gets there).
    Commits the contributions' state after each solve."""
    scale = 1.0
    for _ in range(o.stabilisation_polish):
        stats.polish_solves += 1
        hist: list[float] = []
        try:
            u = _increment(newton, u, 1.0, gravity, dirichlet, hist)
            stats.residual_history.append(hist)
            for c in newton.contribs:
                c.commit(u.reshape(-1, 3))
            newton.damped_last = False
            return u
        except _Failed:
            for c in newton.contribs:
                c.rollback()
        try:
            u = _stabilised_increment(newton, u, 1.0, gravity, dirichlet, hist, scale)
        except _Failed:
            for c in newton.contribs:
                c.rollback()
            scale *= 4.0  # stiffer damping: a smaller, easier proximal step
            continue
        stats.residual_history.append(hist)
        for c in newton.contribs:
            c.commit(u.reshape(-1, 3))
        scale = max(0.5 * scale, 1.0 / 64.0)
    raise _Failed(f"no undamped equilibrium after {o.stabilisation_polish} stabilised solves")


def _increment(newton: _Newton, u: np.ndarray, t: float, gravity, dirichlet, hist,
               multipliers: Sequence[tuple[Any, Any]] = ()) -> np.ndarray:
    """Newton solve of the increment ending at ``t``, then the augmented-Lagrangian loop:
    ``multipliers`` (a settle, see :func:`_increment_with_retries`): (contribution,
    trial state) pairs whose multipliers the solve starts from instead of the committed
    ones.  While a contribution updates its multipliers (``augment`` returns False), re-solve; a
    contribution whose multipliers have stopped converging (its ``stalled`` message, see
    :meth:`.contact.PlateContact._check_stall`) fails the increment at once (cut-back),
    counted in ``stalled_augmentations``.

    With ``augmentation = "final"`` an undamped increment that ends before ``t = 1`` skips
    the loop: each contribution takes one Uzawa update of its multipliers instead
    (``carry_multipliers``), which the caller's commit carries into the next increment,
    whose plate motion the solve has to follow anyway.  The penetration of those
    intermediate states is bounded by the penalty alone (about ``p / eps``); the step's last
    increment iterates the multipliers to ``penetration_tol_mm``, and only that state is
    returned.  Stabilised (damped) increments keep the loop: their state is not an
    equilibrium to carry multipliers from.  ``"final"`` saves about a fifth of the Newton
    iterations over the Pelicano protocols (docs/performance-mechanics.md).

    With ``augmentation_force_tol > 0`` (opt-in) the solves of an increment stop at that
    looser relative residual while its multipliers are still being updated (after at least
    one Newton iteration; no displacement test).  Once a state passes the multiplier check
    it is solved to ``force_tol`` with the same multipliers (``tightening_solves``) and
    checked again, so the returned state meets the same criteria as without the option.
    It is not the default because it can send a frictional compression along another path
    (more tissue pinched at the chest wall) at several times the cost."""
    p, o = newton.p, newton.o
    for c in newton.contribs:
        c.set_time(t)
    for c, state in multipliers:  # a settle: the stabilised solve's multipliers
        c.set_trial_state(state, solve_state=False)
    fext = body_force(p, gravity(t)) if gravity is not None else np.zeros(p.n_dofs)
    dofs, vals = _constraint_targets(p, u, dirichlet, t)
    it0 = newton.stats.iterations
    guess, newton.guess = newton.guess, None
    start = u if guess is None else newton.start(u, guess, fext, newton.constraints(dofs))
    final = o.augmentation == "final" and t < 1.0 - 1e-12 and newton.damping is None
    # inexact solves while the multipliers move (augmentation_force_tol); the state that
    # passes the multiplier check is then solved to force_tol and checked again
    loose = (o.augmentation_force_tol if o.augmentation_force_tol > 0 and not final
             and newton.contribs else None)
    newton.increment_start = True
    u_new = newton.solve_increment(start, fext, dofs, vals, hist, u_base=u, loose_tol=loose)
    newton.first_solve_iterations = newton.stats.iterations - it0
    _log_solve(newton, t, "inexact solve" if loose else "solve", newton.first_solve_iterations,
               hist)
    if final:
        for c in newton.contribs:
            carry = getattr(c, "carry_multipliers", None)
            if carry is not None:
                carry(u_new.reshape(-1, 3))
        return u_new
    updates = 0
    while True:
        done = [c.augment(u_new.reshape(-1, 3)) for c in newton.contribs]
        it1 = newton.stats.iterations
        if all(done):
            if loose is None:
                return u_new
            loose = None  # same multipliers, to the full tolerance; then checked again
            newton.stats.tightening_solves += 1
            u_new = newton.solve_increment(u_new, fext, dofs, vals, hist, u_base=u)
            _log_solve(newton, t, "solve to force_tol", newton.stats.iterations - it1, hist)
            continue
        stalled = [c for c in newton.contribs if getattr(c, "stalled", "")]
        if stalled:
            newton.stats.stalled_augmentations += 1
            c = stalled[0]
            raise _Stalled(c.stalled, getattr(c, "stalled_at", None) or c.stalled)
        if updates == o.max_augmentations:
            break
        updates += 1
        newton.stats.augmentations += 1
        u_new = newton.solve_increment(u_new, fext, dofs, vals, hist, u_base=u, loose_tol=loose)
        _log_solve(newton, t, "re-solve after a multiplier update", newton.stats.iterations - it1,
                   hist)
        if updates == o.max_augmentations and loose is None:
            break  # the last exact re-solve is not checked; an inexact one is, so that a
            # state passing the check still gets its tightening solve
    raise _Failed(f"augmented-Lagrangian multipliers not converged after {o.max_augmentations} updates")


def _log_solve(newton: _Newton, t: float, what: str, iterations: int, hist: list[float]) -> None:
    """DEBUG record of one converged Newton solve of an increment (``regtrack --debug``):
    where a step's iterations go, first solves against augmented-Lagrangian re-solves."""
    if log.isEnabledFor(logging.DEBUG):
        log.debug("%s: increment to t = %.4g, %s%s: %d Newton iterations, |R| = %.3g N",
                  newton.stats.name, t, "stabilised " if newton.damping is not None else "", what,
                  iterations, hist[-1] if hist else float("nan"))


def reaction_forces(problem: Problem, u: np.ndarray, *, gravity_ms2=None,
                    contributions: Sequence[Contribution] = ()) -> np.ndarray:
    """Residual ``f_int + sum r_c - f_ext`` (N, 3) N at ``u``: at constrained nodes this is
    the force the supports exert on the body; at free nodes it is ~0 after convergence."""
    R = evaluate(problem, u, want_k=False).f
    for c in contributions:
        R = R + np.asarray(c.residual_tangent(np.asarray(u).reshape(-1, 3))[0]).reshape(-1)
    if gravity_ms2 is not None:
        R = R - body_force(problem, gravity_ms2)
    return R.reshape(-1, 3)
