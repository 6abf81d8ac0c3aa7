"""Quasi-static load steps as minimisations of the incremental potential.

Each increment of a load step (pseudo-time ``t``) finds the displacement ``u`` (mm) that
minimises

.. math::

    \\Pi(u) = W(u) - f_{ext}(t) \\cdot u + \\sum_{plates} (\\Pi_N + \\Pi_T)(u)
    \\quad\\text{(N mm)}

over the free dofs (the chest-wall nodes keep their displacement): ``W`` the stored energy
of the tissue and the skin membrane (:mod:`.problem`; the ANP tetrahedron and the
tension-field membrane are variational), ``f_ext`` gravity, and the plates' augmented-
Lagrangian contact and lagged friction potentials (:mod:`.potential`).

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

Increments: a plate move is split into increments of at most ``max_plate_increment_mm`` of
travel (friction is path dependent), a gravity change into ``1 / initial_increment``. Each
increment starts from the last state or the path extrapolated linearly from the last two,
whichever has the lower potential, and its multipliers and friction-bound pressures from
theirs extrapolated the same way (a start changes the iterations, not the minimiser). The
augmented-Lagrangian multipliers and the friction lag of every increment are iterated
(relaxed updates, :meth:`.potential.PlatePotential.update`) until the penetration is below
``penetration_tol_mm`` and the lagged slip bound agrees with the current pressure within
``friction_tol`` of the plate's normal force (or of the load scale ``F_ref`` when that is
larger: a plate that barely touches): each increment is a backward-Euler step of Coulomb's
law at its own pressure, so the frictional path does not carry a lag from one increment
into the next. An increment that does not converge, in ``4 max_iterations`` Newton
iterations or in ``max_augmentations`` multiplier updates, is halved (down to 1/64 of its
length), the last one of a step too: no tolerance is relaxed. With friction the state at
the end of a step depends on the path, and a shorter increment is a different, closer lag
problem whose start is nearer its fixed point.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from regtrack.errors import ContactDidNotConvergeError, SolverDidNotConvergeError
from regtrack.mechanics.linsolve import LinearSolveError, LinearSolver, serial_openblas
from regtrack.mechanics.potential import PlateEval, PlatePotential
from regtrack.mechanics.problem import (Problem, body_force, chest_wall_reaction, constraint_positions, dof_nodes,
                                        evaluate, force_balance, scatter_add, system_matrix)
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
#: Absolute floor (N) of the force reference, so that an unloaded state still has one.
FORCE_FLOOR_N = 1e-9


@dataclass
class _State:
    """Potential, residual and (optionally) the assembled pieces at one ``u``."""

    u: np.ndarray
    energy: float
    R: np.ndarray
    plates: list[PlateEval]
    ev: object = None
    f_ref: float = 0.0


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
        # every iteration lowers the potential, so a minimisation may take longer than a
        # Newton solve of the residual before an increment is halved
        self.max_iterations = 4 * options.max_iterations
        self.stats = StepStats()

    # -- the potential ------------------------------------------------------------------
    def state(self, u: np.ndarray, fext: np.ndarray, plates: Sequence[PlatePotential], *,
              hessian: bool) -> _State | None:
        """``Pi``, ``R = dPi/du`` and the pieces of the Hessian at ``u`` (None if an element
        inverts)."""
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
        self.stats.t_assembly += time.perf_counter() - t0
        weight = float(np.linalg.norm(fext.reshape(-1, 3).sum(axis=0)))
        reaction = float(np.linalg.norm(chest_wall_reaction(self.p, ue, R)))
        f_ref = max(weight, fc, reaction, float(np.linalg.norm(ev.f)) / np.sqrt(len(ev.f)),
                    FORCE_FLOOR_N)
        return _State(ue.reshape(-1, 3), energy, R, pe, ev, f_ref)

    def converged(self, s: _State) -> bool:
        norm = float(np.linalg.norm(s.R[self.free]))
        resultant = float(np.linalg.norm(self.free_resultant(s.R)))
        return norm <= self.o.force_tol * s.f_ref and resultant <= self.o.balance_tol * s.f_ref

    def free_resultant(self, R: np.ndarray) -> np.ndarray:
        """The resultant (3,) N of the residual's free components (a node may be held in
        some directions only: symmetry rollers)."""
        return np.where(self.free, R, 0.0).reshape(-1, 3).sum(axis=0)

    # -- Newton ---------------------------------------------------------------------------
    def matrix(self, s: _State, ev, shift: float) -> sp.csr_matrix:
        """The system matrix (ANP: augmented) of the tissue evaluation ``ev`` at ``s`` with the
        contact Hessians, ``shift`` added to the free displacement diagonal, and identity
        rows/columns at the fixed dofs."""
        data = ev.data.copy()
        pat = self.p.pattern
        for e in s.plates:
            if e.hess is not None and e.hess.nnz:
                scatter_add(data, pat.dof_positions(e.hess.row, e.hess.col), e.hess.data)
        if shift > 0:
            data[self._diag] += shift
        M = system_matrix(self.p, ev, data)
        zero, diag = self._cons
        M.data[zero] = 0.0
        M.data[diag] = 1.0
        return M

    def direction(self, s: _State) -> np.ndarray:
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

    def line_search(self, s: _State, du: np.ndarray, fext: np.ndarray,
                    plates: Sequence[PlatePotential]) -> _State | None:
        """Backtracking (halving) on ``Pi`` from the full step; None when no trial of 40
        lowers it.

        A full step that lowers ``Pi`` by more than ``EXPAND_RATIO`` times what the
        quadratic model predicts (``-R . du / 2``) has met less curvature than the
        Hessian holds: the projection onto the positive semi-definite cone clamps the
        negative curvature of a path that snaps (a region slipping on a plate, the skin
        turning over a plate's edge), and full steps then creep along it by hundredths of a
        millimetre.  The step is doubled while ``Pi`` keeps falling (at most ``2^6``); the
        lowest trial is taken."""
        slope = float(s.R[self.free] @ du[self.free])
        scale = 1e-12 * (abs(s.energy) + float(np.abs(fext) @ np.abs(s.u.reshape(-1))) + 1e-12)
        a = 1.0
        for k in range(40):
            self.stats.line_search_trials += 1
            trial = self.state(s.u + a * du.reshape(-1, 3), fext, plates, hessian=False)
            if trial is not None and trial.energy <= s.energy + ARMIJO_C * a * slope + scale:
                if k == 0 and trial.energy - s.energy < EXPAND_RATIO * 0.5 * slope:
                    trial = self._expand(s, trial, du, fext, plates)
                return trial
            a *= 0.5
        return None

    def _expand(self, s: _State, best: _State, du: np.ndarray, fext: np.ndarray,
                plates: Sequence[PlatePotential]) -> _State:
        """The lowest of ``Pi(u + 2^k du)``, k = 1..6, while it keeps falling (``best``: k = 0)."""
        a = 1.0
        for _ in range(6):
            a *= 2.0
            self.stats.line_search_trials += 1
            trial = self.state(s.u + a * du.reshape(-1, 3), fext, plates, hessian=False)
            if trial is None or trial.energy >= best.energy:
                break
            best = trial
        return best

    def solve(self, u: np.ndarray, fext: np.ndarray, plates: Sequence[PlatePotential]) -> _State:
        """Minimise ``Pi`` from ``u`` (N, 3) at fixed loads and lags; raises
        :class:`SolverDidNotConvergeError` after ``max_iterations``."""
        s = self.state(u, fext, plates, hessian=True)
        if s is None:
            raise SolverDidNotConvergeError("an element is inverted at the start of the increment")
        for _ in range(self.max_iterations):
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
        raise SolverDidNotConvergeError(
            f"no equilibrium in {self.max_iterations} Newton iterations (|R| = "
            f"{np.linalg.norm(s.R[self.free]):.3g} N, reference {s.f_ref:.3g} N; {self.where(s, plates)})")

    def where(self, s: _State, plates: Sequence[PlatePotential]) -> str:
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


Progress = Callable[[str, float], None]


def minimise_step(problem: Problem, u0: np.ndarray, *, gravity: Callable[[float], np.ndarray] | None = None,
                  contacts: Sequence = (), n_increments: int = 1, options=None, config=None,
                  dirichlet: Callable[[float], tuple] | None = None,
                  forces: Callable[[float], np.ndarray] | None = None, T0_mm: float | None = None,
                  progress: Progress | None = None, step_name: str = ""
                  ) -> tuple[np.ndarray, StepStats, np.ndarray]:
    """Run one load step from ``u0`` (N, 3) mm over ``n_increments`` equal increments of
    pseudo-time; ``gravity(t)`` (m/s^2, model frame; None: no weight); ``contacts`` the step's
    :class:`~.contact.PlateContact` objects (their ``set_time`` moves the plates), whose
    committed states are updated; ``config`` the :class:`~.contact.ContactConfig`
    (penetration and friction tolerances, penalty growth).  Returns ``u`` at ``t = 1``, the
    step's statistics and the residual ``dPi/du`` (N, 3) N there (at the fixed nodes: the
    support force on the body).  ``dirichlet(t) -> (dofs, values)``: displacements (mm)
    prescribed besides the model's fixed nodes (which keep their ``u0``), set at the start
    of each increment.  ``forces(t)``: dead (non-follower) nodal forces (N, 3) in N, a
    prescribed point, edge or traction load (:func:`.loads.traction_forces`), whose
    potential ``-f . u`` joins the weight's.  ``progress(step_name, t, force_N=..., D=...)`` after each increment:
    the upper plate's force (N) and, given the uncompressed thickness ``T0_mm``, the
    compression degree ``1 - gap / T0``.  Raises :class:`SolverDidNotConvergeError` with
    ``load_fraction`` and ``last_converged`` when an increment fails at the smallest
    increment."""
    o = options or problem.config.solver
    cfg = config or (contacts[0].config if contacts else None)
    extra = np.zeros(0, np.int64) if dirichlet is None else np.asarray(dirichlet(0.0)[0], np.int64)
    m = Minimiser(problem, o, np.concatenate([problem.fixed_dofs, extra.reshape(-1)]))
    m.stats.name = step_name
    t_start = time.perf_counter()
    u = np.asarray(u0, float).reshape(-1, 3).copy()
    plates = [PlatePotential(c, u) for c in contacts]
    R = np.zeros(u.size)
    previous: tuple[np.ndarray, float] | None = None  # the last increment's start and length
    lagged: list = []  # each plate's multipliers and bound pressures at that start
    t, dt = 0.0, 1.0 / max(int(n_increments), 1)
    base, min_dt = dt, dt / 64.0
    with serial_openblas():
        while t < 1.0 - 1e-12:
            t_new = min(1.0, t + dt)
            try:
                starts = [u]
                if previous is not None:  # the path so far, extrapolated linearly
                    starts.append(u + (t_new - t) / previous[1] * (u - previous[0]))
                    _predict(plates, lagged, (t_new - t) / previous[1])
                if dirichlet is not None:
                    dofs, vals = dirichlet(t_new)
                    for k, v in enumerate(starts):
                        v = v.copy().reshape(-1)
                        v[np.asarray(dofs, np.int64)] = vals
                        starts[k] = v.reshape(-1, 3)
                s = _increment(m, starts, t_new, _external(problem, gravity, forces), contacts, plates, cfg)
            except SolverDidNotConvergeError as exc:
                for pl in plates:
                    pl.begin(u)
                if dt / 2 < min_dt:
                    raise SolverDidNotConvergeError(
                        f"step '{step_name}': no equilibrium at t = {t_new:.4g} from t = {t:.4g} "
                        f"(increments down to {dt:.3g}): {exc}", load_fraction=t,
                        last_converged=u) from exc
                dt /= 2
                m.stats.cutbacks += 1
                log.info("%s: increment to t = %.4g cut back (%s)", step_name, t_new, exc)
                continue
            previous = (u, t_new - t)
            u, t, R = s.u, t_new, s.R
            dt = min(2.0 * dt, base)
            m.stats.increments += 1
            lagged = [(st["lam"], st["pconv"]) for st in (pl.c.get_state() for pl in plates)]
            for pl in plates:
                pl.commit(u)
            if progress is not None:
                progress(step_name, t, **_progress_info(plates, s, T0_mm))
    m.stats.t_total = time.perf_counter() - t_start
    return u, m.stats, R.reshape(-1, 3)


def _predict(plates: Sequence[PlatePotential], lagged: list, ratio: float) -> None:
    """Start each plate's multipliers and friction-bound pressures on the path of the last
    increment, extrapolated by ``ratio`` of its length (clipped at 0), as the start
    displacement is: the multiplier updates then begin near the increment's contact
    pressures instead of the last one's.  A start changes the updates, not the converged
    state."""
    for pl, (lam0, p0) in zip(plates, lagged):
        pl.lam = np.maximum(pl.lam + ratio * (pl.lam - lam0), 0.0)
        pl.pbar = np.maximum(pl.pbar + ratio * (pl.pbar - p0), 0.0)


def _external(problem: Problem, gravity, forces) -> Callable[[float], np.ndarray]:
    """``t -> f_ext(t)`` (3N,) N: the weight under ``gravity(t)`` plus the dead loads ``forces(t)``."""
    def fext(t: float) -> np.ndarray:
        f = np.zeros(problem.n_dofs) if gravity is None else body_force(problem, gravity(t))
        if forces is not None:
            f = f + np.asarray(forces(t), float).reshape(-1)
        return f
    return fext


def _progress_info(plates, s: _State, T0_mm: float | None) -> dict:
    """The upper plate's normal force (N) at state ``s`` and, with ``T0_mm``, the
    compression degree ``D = 1 - gap / T0`` of the plates' current gap."""
    by = {pl.name: (pl, e) for pl, e in zip(plates, s.plates)}
    info: dict = {}
    if "upper" in by:
        pl, e = by["upper"]
        info["force_N"] = -float(pl.c.plate.normal @ e.grad.reshape(-1, 3).sum(axis=0))
    if T0_mm and "upper" in by and "lower" in by:
        lo = by["lower"][0].c.plate
        gap = float((by["upper"][0].c.plate.origin - lo.origin) @ lo.normal)
        info["D"] = 1.0 - gap / T0_mm
    return info


def _increment(m: Minimiser, starts: Sequence[np.ndarray], t: float, external, contacts, plates,
               cfg):
    """One increment to ``t`` from the start of lowest potential among ``starts`` (the last
    state, and the path extrapolated from it: a starting guess changes the iterations, not
    the minimiser): minimise, and update the multipliers and the friction lag until the
    penetration and the friction bound are converged (each increment is then a backward-
    Euler step of Coulomb's law at its own pressure)."""
    for c in contacts:
        c.set_time(t)
    fext = external(t)
    u = starts[0]
    if len(starts) > 1:
        trials = [m.state(v, fext, plates, hessian=False) for v in starts]
        energies = [np.inf if s is None else s.energy for s in trials]
        u = starts[int(np.argmin(energies))] if np.isfinite(min(energies)) else starts[0]
    previous: list = [None] * len(plates)
    n_aug = m.o.max_augmentations
    for k in range(n_aug):
        s = m.solve(u, fext, plates)
        u = s.u
        pen = max((pl.max_violation(e) for pl, e in zip(plates, s.plates)), default=0.0)
        ferr = max((pl.friction_error(e, s.f_ref) for pl, e in zip(plates, s.plates)), default=0.0)
        done = cfg is None or (pen <= cfg.penetration_tol_mm and ferr <= cfg.friction_tol)
        log.debug("%s: t = %.4g, update %d: %d iterations so far, penetration %.3g mm, "
                  "friction error %.3g, |R| %.3g N, resultant %.3g N", m.stats.name, t, k,
                  m.stats.iterations, pen, ferr, np.linalg.norm(s.R[m.free]),
                  np.linalg.norm(m.free_resultant(s.R)))
        if done:
            return s
        for i, (pl, e) in enumerate(zip(plates, s.plates)):
            eps_max = cfg.penalty_growth_max * float(np.max(pl.c.eps_n))
            previous[i] = pl.update(e, growth=cfg.penalty_growth, slow_ratio=cfg.slow_uzawa_ratio,
                                    eps_max=eps_max, previous=previous[i])
        m.stats.augmentations += 1
    raise ContactDidNotConvergeError(f"contact multipliers not converged in {n_aug} updates "
                                     f"(penetration {pen:.3g} mm, friction error {ferr:.3g})")


def minimiser_from_problem(problem: Problem, *, options=None, progress: Progress | None = None):
    """The protocol engine's step solver (:data:`.protocol_run.StepSolver`) with
    :func:`minimise_step`: as the :class:`.protocol_run.StepControl` asks, a plate move in
    increments of ``max_increment`` (its plate travel cap), a single increment, or a
    gravity change in ``1 / initial_increment`` increments.  The stats carry the chest-wall
    reaction (N) and the force balance; a state whose balance misses ``stall_force_tol``
    (0.5 % by default) is never returned."""
    o = options or problem.config.solver

    def solve(u0, g0, g1, contribs, name, control):
        g0 = np.asarray(g0, float)
        g1 = np.asarray(g1, float)
        if control.single:
            n = 1
        elif control.max_increment is not None:
            n = int(np.ceil(1.0 / control.max_increment - 1e-9))
        else:
            n = int(np.ceil(1.0 / o.initial_increment - 1e-9))
        cfg = contribs[0].config if contribs else None
        u, st, r = minimise_step(problem, u0, gravity=lambda t: g0 + t * (g1 - g0), contacts=contribs,
                                 n_increments=n, options=o, config=cfg, progress=progress,
                                 step_name=name, T0_mm=control.T0_mm)
        out = st.to_dict()
        fixed = problem.model.fixed
        if fixed.any():
            out["chest_wall_reaction_N"] = chest_wall_reaction(problem, u, r).tolist()
            fb = force_balance(problem, u, r, g1, contribs, o.stall_force_tol)
            out["force_balance"] = fb
            if not fb["ok"]:
                raise SolverDidNotConvergeError(
                    f"step '{name}': the forces do not balance ({100 * fb['relative']:.2g} % of "
                    f"{fb['load_N']:.3g} N; allowed {100 * fb['tol']:.2g} %)", load_fraction=1.0,
                    last_converged=u)
        return u, out
    return solve
