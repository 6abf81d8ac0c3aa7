"""Quasi-static load steps as minimisations of the incremental potential.

Each increment of a load step (pseudo-time ``t``) finds the displacement ``u`` (mm) that
minimises

.. math::

    \\Pi(u) = W(u) - f_{ext}(t) \\cdot u + \\sum_{plates} (\\Pi_N + \\Pi_T)(u) + \\Pi_S(u)
    \\quad\\text{(N mm)}

over the free dofs (the chest-wall nodes keep their displacement): ``W`` the stored energy
of the tissue and the skin membrane (:mod:`.problem`; the ANP tetrahedron and the
tension-field membrane are variational), ``f_ext`` gravity, the plates' augmented-
Lagrangian contact and lagged friction potentials (:mod:`.potential`), and ``Pi_S`` the
outer surface's self-contact barrier (:mod:`.selfcontact`; when the problem has one).

Each increment's minimisation at fixed loads and lags is :class:`.newton.Minimiser`: Newton
with a positive definite Hessian, backtracking on ``Pi`` and a convergence test on the
residual, its resultant and the last correction.

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
into the next. A minimisation followed by an update is inexact (its residual within a
fifth of the friction tolerance, :func:`_inexact_scale`); the state an increment ends with
meets the full tolerances.

The first minimisation of an increment may end as a predictor: its lag, extrapolated from
the last two increments, is off by 1.5 to 3.6 % of the plate force (the benchmark
hemisphere), far more than a later update leaves, so when the first Newton iteration from
the start takes the whole Newton step and leaves a residual below that lag's friction-force
error (:meth:`.newton.Minimiser.lag_dominates`), the lag is updated from there, by a plain
update (``omega = 1``) that does not enter Aitken's secant. A start outside Newton's local
region (a damped first step) is minimised as any other. Measured on eight real exams: 7 to
8 % fewer Newton iterations, the end states within 0.013 mm (docs/performance-mechanics.md).

An increment that does not converge, in ``4 max_iterations`` Newton iterations or in
``max_augmentations`` multiplier updates, is halved (down to 1/64 of its length), the last
one of a step too: no tolerance is relaxed. With friction the state at the end of a step
depends on the path, and a shorter increment is a different, closer lag
problem whose start is nearer its fixed point.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from regtrack.errors import ContactDidNotConvergeError, SolverDidNotConvergeError
from regtrack.mechanics.linsolve import serial_openblas
from regtrack.mechanics.newton import Minimiser, NewtonState
from regtrack.mechanics.potential import PlatePotential
from regtrack.mechanics.problem import Problem, body_force, chest_wall_reaction, force_balance
from regtrack.mechanics.support import WallSupport
from regtrack.mechanics.types import StepStats

log = logging.getLogger(__name__)

Progress = Callable[[str, float], None]


def minimise_step(problem: Problem, u0: np.ndarray, *, gravity: Callable[[float], np.ndarray] | None = None,
                  contacts: Sequence = (), n_increments: int = 1, options=None, config=None,
                  dirichlet: Callable[[float], tuple] | None = None,
                  forces: Callable[[float], np.ndarray] | None = None, T0_mm: float | None = None,
                  support: Callable[[float], WallSupport] | None = None,
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
    potential ``-f . u`` joins the weight's.  ``support(t)``: the chest-wall support
    (:class:`.support.WallSupport`) at pseudo-time ``t``, a support released over the step
    as a load is applied (None: the problem's own, unchanged).  ``progress(step_name, t,
    force_N=..., D=...)`` after each increment: the upper plate's force (N) and, given the
    uncompressed thickness ``T0_mm``, the compression degree ``1 - gap / T0``; and
    ``progress(step_name, t, working_to=t_new, newton=k, updates=j)`` after every Newton
    iteration of the increment being solved (``k`` iterations and ``j`` multiplier updates
    so far in this attempt at it), so that an increment that takes minutes still shows it
    moves.  Raises :class:`SolverDidNotConvergeError` with
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
    own_support = problem.support
    t_new, its0, aug0 = dt, 0, 0
    if progress is not None:
        def pulse() -> None:
            progress(step_name, t, working_to=t_new, newton=m.stats.iterations - its0,
                     updates=m.stats.augmentations - aug0)
        m.on_iteration = pulse
    try:
        with serial_openblas():
            while t < 1.0 - 1e-12:
                t_new = min(1.0, t + dt)
                its0, aug0 = m.stats.iterations, m.stats.augmentations
                if support is not None:
                    problem.support = support(t_new)
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
                    s = _increment(m, u, starts, t_new, _external(problem, gravity, forces), contacts,
                                   plates, cfg)
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
    finally:
        problem.support = own_support
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


def _progress_info(plates, s: NewtonState, T0_mm: float | None) -> dict:
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


def _increment(m: Minimiser, origin: np.ndarray, starts: Sequence[np.ndarray], t: float, external,
               contacts, plates, cfg):
    """One increment to ``t`` from the start of lowest potential among ``starts`` (the last
    state ``origin``, and the path extrapolated from it: a starting guess changes the
    iterations, not the minimiser; a start that the outer surface cannot reach from
    ``origin`` without crossing itself is not taken): minimise, and update the multipliers
    and the friction lag until the penetration and the friction bound are converged (each
    increment is then a backward-Euler step of Coulomb's law at its own pressure)."""
    for c in contacts:
        c.set_time(t)
    fext = external(t)
    if not m.reachable(origin, starts[0]):
        raise SolverDidNotConvergeError("the prescribed displacements move the outer surface "
                                        "through itself")
    u = starts[0]
    if len(starts) > 1:
        trials = [m.state(v, fext, plates, hessian=False) if m.reachable(origin, v) else None
                  for v in starts]
        energies = [np.inf if s is None else s.energy for s in trials]
        u = starts[int(np.argmin(energies))] if np.isfinite(min(energies)) else starts[0]
    previous: list = [None] * len(plates)
    n_aug = m.o.max_augmentations
    # an inner minimisation whose multipliers will be updated stops at this multiple of the
    # force tolerances (_inexact_scale); the state an increment returns meets them in full
    scale = _inexact_scale(m.o, cfg)
    loose, start = True, None
    k = 0
    while True:
        s = m.solve(u, fext, plates, loose=scale if loose else 0.0, start=start,
                    predictor=k == 0 and loose)
        predicted = k == 0 and loose and not m.converged(s, scale)  # stopped as the predictor
        start = None
        u = s.u
        pen = max((pl.max_violation(e) for pl, e in zip(plates, s.plates)), default=0.0)
        ferr = max((pl.friction_error(e, s.f_ref) for pl, e in zip(plates, s.plates)), default=0.0)
        done = cfg is None or (pen <= cfg.penetration_tol_mm and ferr <= cfg.friction_tol)
        log.debug("%s: t = %.4g, update %d%s: %d iterations so far, penetration %.3g mm, "
                  "friction error %.3g, |R| %.3g N, resultant %.3g N", m.stats.name, t, k,
                  " (inexact)" if loose else "", m.stats.iterations, pen, ferr,
                  np.linalg.norm(s.R[m.free]), np.linalg.norm(m.free_resultant(s.R)))
        if done and not loose:
            return s
        if done:  # the contact holds: minimise to the full tolerance at these multipliers
            loose, start = False, s
            continue
        if k + 1 == n_aug:  # the multipliers of n_aug updates tried
            break
        for i, (pl, e) in enumerate(zip(plates, s.plates)):
            eps_max = cfg.penalty_growth_max * float(np.max(pl.c.eps_n))
            step = pl.update(e, growth=cfg.penalty_growth, slow_ratio=cfg.slow_uzawa_ratio,
                             eps_max=eps_max, previous=previous[i])
            previous[i] = None if predicted else step  # a predictor's step is no secant
        m.stats.augmentations += 1
        k += 1
        loose = True
    raise ContactDidNotConvergeError(f"contact multipliers not converged in {n_aug} updates "
                                     f"(penetration {pen:.3g} mm, friction error {ferr:.3g})")


def _inexact_scale(o, cfg) -> float:
    """The factor on the force tolerances of an inexact inner minimisation, before a
    multiplier and friction-lag update: the residual may be as large as a fifth of the
    friction bound's tolerance (``friction_tol`` of the same force reference ``F_ref``),
    so that the lag update sees the contact pressures to well within what it is judged by
    (20 at the defaults; measurements in docs/performance-mechanics.md).  Without contact:
    1 (only the correction test is skipped)."""
    if cfg is None:
        return 1.0
    return max(1.0, cfg.friction_tol / (5.0 * o.force_tol))


def minimiser_from_problem(problem: Problem, *, options=None, progress: Progress | None = None):
    """The protocol engine's step solver (:data:`.protocol_run.StepSolver`) with
    :func:`minimise_step`: as the :class:`.protocol_run.StepControl` asks, a plate move in
    increments of ``max_increment`` (its plate travel cap), a single increment, or a
    gravity change in ``1 / initial_increment`` increments.  Once both plates hold the
    breast the chest-wall layer's far side moves with them (``control.body_motion``,
    :meth:`.support.WallSupport.moved`).  The stats carry the chest-wall
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
        layer = problem.support
        moved = None
        if layer is not None and control.body_motion is not None:
            def moved(t):
                return layer.moved(control.body_motion(t))
            problem.support = moved(1.0)  # the step's end: its reaction and balance
        try:
            u, st, r = minimise_step(problem, u0, gravity=lambda t: g0 + t * (g1 - g0), contacts=contribs,
                                     n_increments=n, options=o, config=cfg, progress=progress,
                                     step_name=name, T0_mm=control.T0_mm, support=moved)
            out = st.to_dict()
            if problem.model.fixed.any():
                out["chest_wall_reaction_N"] = chest_wall_reaction(problem, u, r).tolist()
                fb = force_balance(problem, u, r, g1, contribs, o.stall_force_tol)
                out["force_balance"] = fb
                if not fb["ok"]:
                    raise SolverDidNotConvergeError(
                        f"step '{name}': the forces do not balance ({100 * fb['relative']:.2g} % of "
                        f"{fb['load_N']:.3g} N; allowed {100 * fb['tol']:.2g} %)", load_fraction=1.0,
                        last_converged=u)
        finally:
            problem.support = layer
        return u, out
    return solve
