"""Consistent tangent (finite differences), quadratic Newton convergence, failure modes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from regtrack.errors import SolverDidNotConvergeError
from regtrack.mechanics import problem as P
from regtrack.mechanics import solver as S
from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.mechanics.meshes import box_model
from regtrack.mechanics.p2 import model_to_p2


def heterogeneous_box():
    m = box_model((3.0, 2.0, 2.0), (3, 2, 2))
    centre = m.points[m.tets].mean(axis=1)
    m.region[np.linalg.norm(centre - [1.5, 1.0, 1.0], axis=1) < 0.7] = 2  # a stiff tumour
    return m


@pytest.mark.parametrize("formulation", ["p1-anp", "p1", "p2"])
def test_tangent_matches_finite_differences(formulation):
    """Relative error of K d vs central differences of the internal force < 1e-6
    (central differences with h = 1e-6 mm have truncation ~h^2 and round-off ~1e-10)."""
    cfg = MechanicsConfig(formulation=formulation, nu=0.49, skin_enabled=formulation != "p2")
    model = heterogeneous_box()
    pr = S.build_problem(model_to_p2(model) if formulation == "p2" else model, cfg)
    assert np.any(pr.mats.c1 > pr.mats.c1.min())
    rng = np.random.default_rng(0)
    u = (0.1 if formulation != "p2" else 0.03) * rng.standard_normal(pr.X.shape)  # no inversion
    K = S.tangent(pr, u)
    assert abs(K - K.T).max() < 1e-12 * abs(K).max()  # variational: symmetric
    for _ in range(3):
        d = rng.standard_normal(u.shape)
        h = 1e-6
        fd = (S.internal_force(pr, u + h * d) - S.internal_force(pr, u - h * d)).reshape(-1) / (2 * h)
        an = K @ d.reshape(-1)
        assert np.linalg.norm(fd - an) / np.linalg.norm(an) < 1e-6
    # forces are the gradient of the stored energy
    d = rng.standard_normal(u.shape)
    e = [P.evaluate(pr, u + s * 1e-6 * d, want_k=False).energy for s in (1, -1)]
    assert (e[0] - e[1]) / 2e-6 == pytest.approx(S.internal_force(pr, u).reshape(-1) @ d.reshape(-1), rel=1e-6)


@pytest.mark.parametrize("formulation", ["p1-anp", "p1"])
def test_newton_converges_quadratically(formulation):
    """Large shear + compression in one increment: once in the asymptotic range the
    residual ratio r_{k+1} / r_k^2 stays bounded while r_k drops by many decades."""
    cfg = MechanicsConfig(formulation=formulation, nu=0.49)
    pr = S.build_problem(heterogeneous_box(), cfg)
    X = pr.X
    bottom, top = np.flatnonzero(X[:, 2] < 1e-9), np.flatnonzero(X[:, 2] > 2 - 1e-9)
    dofs = np.concatenate([(3 * bottom[:, None] + np.arange(3)).ravel(), (3 * top[:, None] + np.arange(3)).ravel()])
    target = np.concatenate([np.zeros(3 * len(bottom)), np.tile([0.4, 0.0, -0.3], len(top))])
    # exact Newton (a fresh factorisation per iteration, solves to 1e-10): the test of the tangent
    opts = SolverOptions(initial_increment=1.0, line_search=False, force_tol=1e-12, disp_tol=1e-12,
                         reuse_factorisation=False)
    u, st = S.solve_step(pr, np.zeros_like(X), dirichlet=lambda t: (dofs, t * target), options=opts)
    hist = np.array(st.residual_history[0][1:])  # [0] is before the prescribed increment
    assert st.increments == 1 and hist[-1] < 1e-12 * hist[0]
    # regression: the pattern stays fixed, so the sparse analysis runs once, not per iteration
    if st.factorisations:
        assert st.analyses <= 1 and st.factorisations == st.iterations
    tail = hist[hist > 1e-11 * hist[0]][-3:]
    # quadratic: log r_{k+1} ~ 2 log r_k (relative to the first residual)
    rel = tail / hist[0]
    orders = np.log(rel[1:]) / np.log(rel[:-1])
    assert np.all(orders > 1.7), (hist, orders)


def test_failure_keeps_last_converged_state_and_load_fraction():
    """Pulling one node through the body inverts elements: cut-backs until the minimum
    increment, then SolverDidNotConvergeError with the load fraction reached."""
    cfg = MechanicsConfig(formulation="p1", nu=0.45, skin_enabled=False)
    m = box_model((2.0, 2.0, 2.0), (2, 2, 2))
    m.fixed = m.points[:, 2] < 1e-9
    pr = S.build_problem(m, cfg)
    node = int(np.argmax(pr.X @ [1, 1, 1]))
    dofs = 3 * node + np.arange(3)
    # stall acceptance off: every accepted increment is converged to force_tol (checked below)
    opts = SolverOptions(initial_increment=0.25, min_increment=0.01, max_iterations=8,
                         stall_force_tol=0.0)
    with pytest.raises(SolverDidNotConvergeError) as exc:
        S.solve_step(pr, np.zeros_like(pr.X), dirichlet=lambda t: (dofs, t * np.array([-6.0, -6.0, -6.0])),
                     options=opts, step_name="pull")
    err = exc.value
    assert 0.0 < err.load_fraction < 1.0
    assert "load fraction" in str(err) and "pull" in str(err)
    u_last = err.last_converged
    assert u_last.shape == pr.X.shape and np.all(np.isfinite(u_last))
    # the kept state is the converged one at that load fraction
    assert np.allclose(u_last[node], err.load_fraction * np.array([-6.0, -6.0, -6.0]))
    R = S.reaction_forces(pr, u_last)
    free = np.ones(pr.n_nodes, bool)
    free[node] = False
    free[m.fixed] = False
    # converged to the solver's tolerance: |R_free| <= force_tol * F_ref, F_ref = the
    # reaction here (the only load)
    assert np.linalg.norm(R[free]) <= opts.force_tol * np.linalg.norm(R[~free])


class _Chatter:
    """A force that flips sign across a plane, like a contact node switching state: at
    dof ``dof`` the residual gets ``a * sign(u - u0)``.  With ``u0`` at the smooth
    equilibrium the combined residual has no root (it jumps from -a to +a there), so
    Newton cycles with ``|R| ~ a`` whatever the number of iterations."""

    name = "chatter"

    def __init__(self, n_dofs, dof, u0, a):
        self.n, self.dof, self.u0, self.a = n_dofs, dof, u0, a

    def begin_step(self, step): ...
    def set_time(self, t): ...
    def commit(self, u): ...
    def rollback(self): ...
    def augment(self, u): return True
    def report(self, u): return {}

    def residual_tangent(self, u):
        r = np.zeros(self.n)
        r[self.dof] = self.a * (1.0 if u.reshape(-1)[self.dof] >= self.u0 else -1.0)
        return r, None


def _sagging_box_with_chatter(formulation: str):
    """A 2 mm box sagging under 1000 m/s^2 (a force of ~0.08 N) plus a :class:`_Chatter`
    of a = 5e-4 F_ref at the top node's vertical dof, placed at the smooth equilibrium.
    Returns (problem, gravity, options, chatter, smooth solution, node)."""
    cfg = MechanicsConfig(formulation=formulation, nu=0.45, skin_enabled=False)
    m = box_model((2.0, 2.0, 2.0), (2, 2, 2))
    m.fixed = m.points[:, 2] < 1e-9
    pr = S.build_problem(m, cfg)
    g = lambda t: t * np.array([0.0, 0.0, -1000.0])  # noqa: E731  (m/s^2)
    opts = SolverOptions(initial_increment=1.0, min_increment=0.5)
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    node = int(np.argmax(pr.X @ [0.0, 0.0, 1.0] + 1e-3 * (pr.X @ [1.0, 1.0, 0.0])))
    dof = 3 * node + 2
    f_ref = float(np.linalg.norm(P.body_force(pr, g(1.0))))
    ch = _Chatter(pr.n_dofs, dof, u_ref.reshape(-1)[dof], 5e-4 * f_ref)
    return pr, g, opts, ch, u_ref, node


def test_stalled_newton_accepts_its_best_iterate_below_the_stall_tolerance():
    """A residual that cannot fall below a = 5e-4 F_ref (no root: a force jump at the
    equilibrium) is accepted at its best iterate with the default stall_force_tol (5e-3;
    counted in stalled_accepts, its relative residual reported), and is a failure with 0."""
    pr, g, opts, ch, u_ref, node = _sagging_box_with_chatter("p1-anp")
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts, contributions=[ch])
    assert st.stalled_accepts >= 1
    assert opts.force_tol < st.stalled_residual_max <= opts.stall_force_tol
    # the accepted state is the smooth equilibrium up to the jump's own effect (a / k)
    sag = abs(u_ref[node, 2])
    assert abs(u[node, 2] - u_ref[node, 2]) < 0.02 * sag
    # (without the stabilised retry, which settles this one at the jump within force_tol)
    strict = SolverOptions(initial_increment=1.0, min_increment=0.5, stall_force_tol=0.0, stabilisation="off")
    with pytest.raises(SolverDidNotConvergeError):
        S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=strict, contributions=[ch])


def test_stalled_newton_stops_early_once_it_stagnates_below_the_stall_tolerance():
    """The stalled increment is accepted as soon as the residual stops falling (after 5
    iterations, not after max_iterations): the chattering residual above is flat from
    the second iteration, so the step takes at most 8 iterations instead of 15+."""
    pr, g, opts, ch, _, _ = _sagging_box_with_chatter("p1")
    _, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts, contributions=[ch])
    assert st.stalled_accepts == 1 and st.increments == 1
    assert st.iterations <= 8 < opts.max_iterations


class _Scalar:
    """Stub of the solver state for ``_Newton.line_search``: one dof, ``R(u) = atan(u)``."""

    def __init__(self, merit):
        self.o = SolverOptions(line_search_merit=merit)
        self.stats = S.StepStats()

    def residual(self, u, fext, want_k):
        return np.arctan(u), None, None


class _Free:
    free = np.array([True])


@pytest.mark.parametrize("merit", ["residual", "directional"])
def test_line_search_cuts_the_overshooting_newton_step_of_atan(merit):
    """Newton on atan(u) from u = 2 overshoots to u = -3.54 (|R| grows from 1.107 to
    1.296).  The residual merit accepts a step with Armijo decrease
    |R(a)| <= (1 - 1e-4 a) |R(0)|; the directional one a step where |du.R(a)| fell."""
    st = _Scalar(merit)
    u0 = np.array([2.0])
    R0 = np.arctan(u0)
    du = -(1.0 + u0 ** 2) * R0  # K du = -R
    alpha, R1, _ = S._Newton.line_search(st, u0, du, R0, None, _Free())
    assert 0.0 < alpha < 1.0
    r1 = abs(np.arctan(u0 + alpha * du))[0]
    if merit == "residual":
        assert r1 <= (1.0 - 1e-4 * alpha) * abs(R0[0])
    else:
        assert abs(du[0] * np.arctan(u0 + alpha * du)[0]) <= 0.8 * abs(du[0] * R0[0])


def _hanging_box():
    """A 2 mm P1 box fixed at z = 0 under a strong gravity ramp: the problem and g(t)."""
    cfg = MechanicsConfig(formulation="p1", nu=0.45, skin_enabled=False)
    m = box_model((2.0, 2.0, 2.0), (2, 2, 2))
    m.fixed = m.points[:, 2] < 1e-9
    return S.build_problem(m, cfg), (lambda t: t * np.array([0.0, 0.0, -1000.0]))


def test_auto_merit_retries_a_failed_increment_with_the_residual_line_search(monkeypatch):
    """(stabilisation off) line_search_merit = "auto": an increment that fails with the directional line search
    is solved again with the residual one before any cut-back (counted in merit_retries);
    with "directional" the same failure is a cut-back, and every increment fails."""
    pr, g = _hanging_box()
    real = S._increment
    used = []

    def only_residual(newton, *a, **k):
        used.append(newton.o.line_search_merit)
        if newton.o.line_search_merit != "residual":
            raise S._Failed("directional line search refused (test)")
        return real(newton, *a, **k)

    monkeypatch.setattr(S, "_increment", only_residual)
    # extrapolation off: the forced failures leave the predictor to the retry (test artefact)
    opts = SolverOptions(initial_increment=0.5, min_increment=0.1, stabilisation="off",
                         extrapolation="off")
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    assert st.cutbacks == 0 and st.merit_retries == st.increments >= 2
    assert used[:2] == ["auto", "residual"]
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g,
                            options=SolverOptions(initial_increment=0.5, line_search_merit="residual",
                                                  extrapolation="off"))
    assert np.allclose(u, u_ref, atol=1e-9)
    with pytest.raises(SolverDidNotConvergeError):
        S.solve_step(pr, np.zeros_like(pr.X), gravity=g,
                     options=SolverOptions(initial_increment=0.5, min_increment=0.1,
                                           line_search_merit="directional", stabilisation="off"))


class _Swappable:
    """A do-nothing contribution with two tangents (the contact interface's swap_tangent)."""

    name = "swappable"

    def __init__(self):
        self.alternative, self.swaps = False, 0

    def swap_tangent(self) -> bool:
        self.alternative, self.swaps = not self.alternative, self.swaps + 1
        return True

    def begin_step(self, step): ...
    def set_time(self, t): ...
    def residual_tangent(self, u): return np.zeros(np.size(u)), None  # noqa: E704
    def commit(self, u): ...
    def rollback(self): ...
    def augment(self, u): return True  # noqa: E704
    def report(self, u): return {}  # noqa: E704


def test_a_failed_increment_is_retried_with_the_other_tangent_before_a_cut_back(monkeypatch):
    """(stabilisation off) After the merit retry, an increment that still fails is solved again with the
    contributions' other tangent (tangent_retries), which is switched back afterwards; a
    failure with both is a cut-back as before."""
    pr, g = _hanging_box()
    real = S._increment
    c = _Swappable()
    seen = []

    def only_alternative(newton, *a, **k):
        seen.append((newton.o.line_search_merit, c.alternative))
        if not c.alternative:
            raise S._Failed("default tangent refused (test)")
        return real(newton, *a, **k)

    monkeypatch.setattr(S, "_increment", only_alternative)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, contributions=[c],
                         options=SolverOptions(initial_increment=0.5, min_increment=0.1, stabilisation="off",
                                               extrapolation="off"))
    assert st.cutbacks == 0 and st.tangent_retries == st.merit_retries == st.increments >= 2
    assert seen[:3] == [("auto", False), ("residual", False), ("auto", True)]
    assert not c.alternative and c.swaps == 2 * st.increments  # switched back every time
    monkeypatch.setattr(S, "_increment", real)
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g,
                            options=SolverOptions(initial_increment=0.5, extrapolation="off"))
    assert np.allclose(u, u_ref, atol=1e-9)
    monkeypatch.setattr(S, "_increment", lambda *a, **k: (_ for _ in ()).throw(S._Failed("no (test)")))
    with pytest.raises(SolverDidNotConvergeError):
        S.solve_step(pr, np.zeros_like(pr.X), gravity=g, contributions=[_Swappable()],
                     options=SolverOptions(initial_increment=0.5, min_increment=0.1))


def test_stabilised_solve_is_the_proximal_problem_with_a_consistent_tangent():
    """A stabilised solve about u0 converges (quadratically: consistent tangent) to the
    root of R(u) + c (u - u0) with c = alpha max(diag K(u0), 1 % of its median): checked
    to the solver tolerance, and the damping restrains the sag (|u| below the undamped
    solution's) without changing its direction."""
    pr, g = _hanging_box()
    opts = SolverOptions(stabilisation_factor=0.5, force_tol=1e-10, disp_tol=1e-10)
    newton = S._Newton(pr, [], opts, S.StepStats(), S._linear_solver(pr, opts))
    u0 = np.zeros(pr.n_dofs)
    newton.stabilise(u0)
    c, ref = newton.damping
    kd = P.evaluate(pr, u0).data[pr.pattern.diagonal_positions()]
    assert np.allclose(c, 0.5 * np.maximum(kd, 0.01 * np.median(kd[kd > 0])))
    fext = P.body_force(pr, g(1.0))
    dofs = pr.fixed_dofs
    hist: list[float] = []
    u = newton.solve_increment(u0, fext, dofs, u0[dofs], hist)
    r = hist[1:]
    assert r[-1] < 1e-8 * r[0] and len(r) <= 8, r
    free = np.ones(pr.n_dofs, bool)
    free[dofs] = False
    R = S.reaction_forces(pr, u.reshape(-1, 3), gravity_ms2=g(1.0)).reshape(-1)
    damp = c * (u - u0)
    assert np.linalg.norm((R + damp)[free]) < 1e-8 * np.linalg.norm(fext)
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=SolverOptions(initial_increment=1.0))
    z = int(np.argmax(pr.X[:, 2]))  # a top node
    assert 0.0 < u[3 * z + 2] / u_ref[z, 2] < 1.0


def test_stabilised_increments_end_in_an_undamped_equilibrium(monkeypatch):
    """stabilisation = "auto": increments that fail undamped (forced here) are solved
    stabilised instead of cut back (counted), then settled by an undamped solve at the same
    load; where the settle is refused too, the step ends with undamped equilibrium
    iterations at t = 1 (polish_solves).  Either way the result equals the plain solution
    to 1e-8 mm (all solved to 1e-10).  If even the stabilised solves fail, the error keeps
    the last undamped equilibrium (here the initial state, t = 0), not a damped state."""
    pr, g = _hanging_box()
    real = S._increment
    # every increment stabilised and settled: no skipping in the run (tested below)
    opts = SolverOptions(initial_increment=0.25, min_increment=0.01, force_tol=1e-10,
                         disp_tol=1e-10, stabilised_first_after=0)
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=replace(opts, stabilisation="off"))
    free = np.ones(pr.n_nodes, bool)
    free[pr.fixed_dofs // 3] = False
    weight = np.linalg.norm(P.body_force(pr, g(1.0)))

    tries: dict[float, int] = {}

    def first_undamped_try_fails(newton, u, t, *a, **k):  # every increment; the settle passes
        if newton.damping is None:
            tries[t] = tries.get(t, 0) + 1
            if tries[t] == 1:
                raise S._Failed("undamped increment refused (test)")
        return real(newton, u, t, *a, **k)

    monkeypatch.setattr(S, "_increment", first_undamped_try_fails)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    assert st.cutbacks == 0 and st.stabilised_increments == st.settled_increments == st.increments >= 2
    assert st.polish_solves == 0
    assert np.abs(u - u_ref).max() < 1e-8  # (the sag is 0.3 mm)

    tries.clear()

    def undamped_only_in_the_polish(newton, u, t, *a, **k):
        if newton.damping is None:
            tries[t] = tries.get(t, 0) + 1
            if t < 1.0 - 1e-12 or tries[t] <= 2:  # the increment's own try and its settle
                raise S._Failed("undamped increment refused (test)")
        return real(newton, u, t, *a, **k)

    monkeypatch.setattr(S, "_increment", undamped_only_in_the_polish)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    assert st.cutbacks == 0 and st.stabilised_increments == st.increments >= 2
    assert st.settled_increments == 0 and st.polish_solves == 1
    assert np.abs(u - u_ref).max() < 1e-8
    R = S.reaction_forces(pr, u, gravity_ms2=g(1.0))
    # the solver's force reference: the largest of the load (L2 norm and resultant, i.e. the
    # weight) and the support reaction
    fext = P.body_force(pr, g(1.0))
    f_ref = max(weight, np.linalg.norm(fext.reshape(-1, 3).sum(axis=0)), np.linalg.norm(R[~free]))
    assert np.linalg.norm(R[free]) <= opts.force_tol * f_ref

    def never_undamped(newton, u, t, *a, **k):
        if newton.damping is None:
            raise S._Failed("undamped increment refused (test)")
        return real(newton, u, t, *a, **k)

    monkeypatch.setattr(S, "_increment", never_undamped)
    with pytest.raises(SolverDidNotConvergeError) as exc:
        S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts, step_name="sag")
    assert exc.value.load_fraction == 0.0 and np.all(exc.value.last_converged == 0.0)
    assert "undamped equilibrium" in str(exc.value) and "stabilisation" in str(exc.value)


def test_crawl_guard_stops_a_run_of_small_stabilised_increments(monkeypatch):
    """crawl_guard: from t = 0.3 every new load fails undamped (forced) and the stabilised
    solve only passes for increments of at most 0.005, so the step crawls in settled
    stabilised increments.  Unguarded it crawls to t = 1 (the result is still the plain
    solution); guarded, after ``crawl_increments`` of them in a row the rest, about 0.7 /
    0.005 = 140 increments > ``crawl_remaining`` = 40, stops the step with SolverCrawlError
    at the last equilibrium.  A run that would finish in fewer increments is let through."""
    from regtrack.errors import SolverCrawlError

    pr, g = _hanging_box()
    real = S._increment
    opts = SolverOptions(initial_increment=0.25, min_increment=1e-4, force_tol=1e-10,
                         disp_tol=1e-10, extrapolation="off")
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    done = {"t": 0.0}

    def crawl_from(t_crawl, size):
        def fake(newton, u, t, *a, **k):
            if t > t_crawl + 1e-12 and t > done["t"] + 1e-12:  # a new load past t_crawl
                if newton.damping is None or t - done["t"] > size + 1e-12:
                    raise S._Failed("refused (test)")
            out = real(newton, u, t, *a, **k)
            done["t"] = t
            return out
        return fake

    monkeypatch.setattr(S, "_increment", crawl_from(0.3, 0.005))
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    assert st.stabilised_accepted >= 140 and st.longest_stabilised_run == st.stabilised_accepted
    # every one is settled, but those that skipped their attempt commit it stabilised
    assert st.settled_increments + st.skipped_settles == st.stabilised_accepted
    assert 0 < st.skipped_settles <= st.skipped_undamped  # (skips that were cut back too)
    assert np.abs(u - u_ref).max() < 1e-8

    done["t"] = 0.0
    with pytest.raises(SolverCrawlError, match="crawl_increments") as exc:
        S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts, crawl_guard=True,
                     step_name="sag")
    t_stop = exc.value.load_fraction
    assert 0.3 < t_stop <= 0.3 + opts.crawl_increments * 0.005 + 1e-9
    assert "step 'sag' crawls" in str(exc.value)
    # the kept state is the equilibrium at t_stop (the plain solution there)
    monkeypatch.setattr(S, "_increment", real)
    u_t, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=lambda t: g(t * t_stop),
                          options=replace(opts, initial_increment=1.0))
    assert np.abs(exc.value.last_converged - u_t).max() < 1e-8

    # near the end of the step (about 0.1 / 0.005 = 20 left): let through; guard off: 0
    for start, o in ((0.9, opts), (0.3, replace(opts, crawl_increments=0))):
        done["t"] = 0.0
        monkeypatch.setattr(S, "_increment", crawl_from(start, 0.005))
        u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=o, crawl_guard=True)
        assert st.longest_stabilised_run >= 15 and np.abs(u - u_ref).max() < 1e-8


def test_a_stabilised_run_skips_the_undamped_attempts_but_probes(monkeypatch):
    """stabilised_first_after = 2, stabilised_probe = 4: new loads in t in (0.3, 0.7] fail
    undamped (forced), so each increment there needs stabilisation.  After two in a row the
    next increments go straight to the stabilised solve (``skipped_undamped``), but for every
    fourth from there, which tries undamped first.  Counted exactly, in increments of 0.05:
    the run's 1st and 2nd (t = 0.35, 0.4) try and fail, the 3rd to 5th skip, the 6th (0.6)
    is a probe and fails, the 7th to 9th skip (0.75 too, past the refusals: the price of
    probing), and the probe at 0.8 passes and ends the run; the skipping increments skip
    their settle too.  The result is the plain solution (1e-8 mm).  Off (0), every new load
    tries undamped first."""
    pr, g = _hanging_box()
    real = S._increment
    opts = SolverOptions(initial_increment=0.05, max_increment=0.05, force_tol=1e-10,
                         disp_tol=1e-10, extrapolation="off")
    assert opts.stabilised_first_after == 2 and opts.stabilised_probe == 4  # the defaults
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    tries: list[float] = []  # the loads of the undamped first attempts (not the settles)
    done = {"t": 0.0}

    def fake(newton, u, t, *a, **k):
        if newton.damping is None and t > done["t"] + 1e-12:
            tries.append(t)
            if 0.3 + 1e-12 < t <= 0.7 + 1e-12:
                raise S._Failed("refused (test)")
        out = real(newton, u, t, *a, **k)
        done["t"] = t
        return out

    monkeypatch.setattr(S, "_increment", fake)
    on = replace(opts, stabilised_first_after=2, stabilised_probe=4)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=on)
    assert np.abs(u - u_ref).max() < 1e-8 and st.cutbacks == 0
    in_run = [t for t in tries if 0.3 + 1e-12 < t <= 0.8 + 1e-12]
    assert np.allclose(in_run, [0.35, 0.4, 0.6, 0.8])
    assert st.skipped_undamped == 6 and st.stabilised_accepted == 9
    assert st.longest_stabilised_run == 9 and len(tries) == st.increments - 6 == 14
    assert st.failed_undamped_iterations == 0  # the forced failures are refused at once
    # the skipping increments skip their settle too (stabilised_skip_settle, the default):
    # committed stabilised, as if it had failed; the others settle (here they all pass)
    assert st.skipped_settles == 6 and st.settled_increments == 3

    tries.clear()
    done["t"] = 0.0
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g,
                         options=replace(on, stabilised_skip_settle=False))
    assert np.abs(u - u_ref).max() < 1e-8 and st.skipped_undamped == 6
    assert st.skipped_settles == 0 and st.settled_increments == 9

    tries.clear()
    done["t"] = 0.0
    off = replace(opts, stabilised_first_after=0)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=off)
    assert st.skipped_undamped == 0 and len(tries) == st.increments == 20
    assert np.abs(u - u_ref).max() < 1e-8

    # failed_undamped_iterations: attempts that iterate and then fail count their iterations
    def solved_then_refused(newton, u, t, *a, **k):
        it0 = newton.stats.iterations
        out = real(newton, u, t, *a, **k)
        if newton.damping is None and 0.3 + 1e-12 < t <= 0.4 + 1e-12 and t > done["t"] + 1e-12:
            spent.append(newton.stats.iterations - it0)
            raise S._Failed("refused after solving (test)")
        done["t"] = t
        return out

    spent: list[int] = []
    done["t"] = 0.0
    monkeypatch.setattr(S, "_increment", solved_then_refused)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=off)
    assert len(spent) == 2 and min(spent) >= 1 and st.failed_undamped_iterations == sum(spent)


def test_polish_damps_less_after_each_proximal_solve_that_converges(monkeypatch):
    """The polish at t = 1 halves the proximal weight after each proximal solve that
    converges (a state creeping towards a distant equilibrium gets there in fewer rounds;
    Pelicano exam 10's 10k MLO standing-gravity step) and quadruples it after
    one that fails; the result is still the undamped equilibrium (1e-8 mm)."""
    pr, g = _hanging_box()
    real, real_stab = S._increment, S._stabilised_increment
    opts = SolverOptions(initial_increment=1.0, force_tol=1e-10, disp_tol=1e-10)
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=replace(opts, stabilisation="off"))
    undamped = {"n": 0}
    scales: list[float] = []

    def undamped_fails_five_times(newton, u, t, *a, **k):  # own try, settle, 3 polish rounds
        if newton.damping is None:
            undamped["n"] += 1
            if undamped["n"] <= 5:
                raise S._Failed("undamped increment refused (test)")
        return real(newton, u, t, *a, **k)

    def third_proximal_fails(newton, u, t, gravity, dirichlet, hist, scale=1.0):
        scales.append(scale)
        if len(scales) == 3:
            raise S._Failed("proximal solve refused (test)")
        return real_stab(newton, u, t, gravity, dirichlet, hist, scale)

    monkeypatch.setattr(S, "_increment", undamped_fails_five_times)
    monkeypatch.setattr(S, "_stabilised_increment", third_proximal_fails)
    u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=opts)
    # the increment's own stabilised solve, then polish rounds 1 (1.0: converges, halve),
    # 2 (0.5: refused, x4), 3 (2.0: converges); round 4's undamped solve converges
    assert scales == [1.0, 1.0, 0.5, 2.0]
    assert st.polish_solves == 4
    assert np.abs(u - u_ref).max() < 1e-8


def test_linear_extrapolation_starts_increments_closer_and_reaches_the_same_solution():
    """extrapolation = "linear": from the third increment on, Newton starts from
    u_n + (dt / dt_prev) (u_n - u_n-1) (counted in extrapolated_increments).  The result
    equals the run started from u_n to 1e-8 mm (both solved to 1e-10), and on this smooth
    gravity ramp (eight equal increments of a sagging box) it takes fewer iterations: the
    predictor's error is second order in the increment, that of u_n first order."""
    pr, g = _hanging_box()
    base = dict(initial_increment=0.125, max_increment=0.125, force_tol=1e-10, disp_tol=1e-10,
                disp_abs_tol_mm=1e-12)
    runs = {}
    for mode in ("linear", "off"):
        u, st = S.solve_step(pr, np.zeros_like(pr.X), gravity=g,
                             options=SolverOptions(extrapolation=mode, **base))
        runs[mode] = (u, st)
    (u_on, st_on), (u_off, st_off) = runs["linear"], runs["off"]
    assert st_on.increments == st_off.increments == 8
    assert st_on.extrapolated_increments == 7 and st_off.extrapolated_increments == 0
    assert np.max(np.abs(u_on - u_off)) < 1e-8
    assert st_on.iterations < st_off.iterations, (st_on.iterations, st_off.iterations)


def test_extrapolated_start_is_refused_where_it_inverts_elements_or_raises_the_residual():
    """The predictor is only a starting guess: a guess that inverts an element, or whose
    free-dof residual exceeds that of u_n, is dropped and Newton starts from u_n."""
    pr, g = _hanging_box()
    opts = SolverOptions()
    newton = S._Newton(pr, [], opts, S.StepStats(), S._linear_solver(pr, opts))
    fext = P.body_force(pr, g(1.0))
    cons = newton.constraints(pr.fixed_dofs)
    u0 = np.zeros(pr.n_dofs)
    top = np.flatnonzero(pr.X[:, 2] > 1.9)
    crushed = u0.copy()
    crushed[3 * top + 2] = -3.0  # top face pushed through the 2 mm box: inverted elements
    assert newton.start(u0, crushed, fext, cons) is u0
    away = u0.copy()
    away[3 * top + 2] = +0.5  # stretched upwards, against gravity: a larger residual
    assert newton.start(u0, away, fext, cons) is u0
    u_ref, _ = S.solve_step(pr, np.zeros_like(pr.X), gravity=g, options=SolverOptions(initial_increment=1.0))
    near = 0.9 * u_ref.reshape(-1)
    assert newton.start(u0, near, fext, cons) is near
    assert newton.stats.extrapolated_increments == 1


class _Inverting(_Scalar):
    """As :class:`_Scalar`, but an element "inverts" beyond u = -0.5 (no residual there)."""

    def residual(self, u, fext, want_k):
        return (None, None, None) if u[0] < -0.5 else (np.arctan(u), None, None)


def test_line_search_counts_the_trials_rejected_for_inverted_elements():
    """From u = 2 the Newton step du = -5 * atan(2) = -5.54 inverts at a = 1, 0.5 (u =
    -3.54, -0.77) and not at 0.25 (u = 0.62): two rejected trials, then the merit test."""
    st = _Inverting("residual")
    u0 = np.array([2.0])
    R0 = np.arctan(u0)
    du = -(1.0 + u0 ** 2) * R0
    alpha, _, _ = S._Newton.line_search(st, u0, du, R0, None, _Free())
    assert alpha == 0.25
    assert st.stats.inverted_trials == 2
    assert st.stats.line_search_trials == 3
    assert st.stats.to_dict()["inverted_trials"] == 2
