"""Protocol schema and engine (regtrack.mechanics.protocol / protocol_run) with a mock solver.

The mock "body" is a grid of nodes each tied to its reference position by a spring
(k N/mm) and loaded by a nodal weight: no elasticity coupling, so every expected number
(plate gap for a target D, force balance, gravity sums) follows by hand.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import Delaunay

from regtrack.errors import ConfigError, ResultCheckError, SolverDidNotConvergeError
from regtrack.mechanics.contact import ContactConfig
from regtrack.mechanics.protocol import (ProtocolOverrides, apply_overrides, parse_protocol,
                                         protocol_for_view, shipped_protocol)
from regtrack.mechanics.protocol_run import BodySetup, ProtocolRunner

K_SPRING = 0.05  # N/mm per node
WEIGHT = 0.02 / 9.81  # N per (m/s^2) per node


def _body(side="R"):
    """A 40 x 30 x 30 mm block of nodes: x in [-40, 0] (chest wall at x = -40)."""
    g = np.stack(np.meshgrid(np.linspace(-40, 0, 9), np.linspace(-15, 15, 7),
                             np.linspace(-15, 15, 7), indexing="ij"), -1).reshape(-1, 3)
    tets = Delaunay(g).simplices
    hull = Delaunay(g).convex_hull
    fixed = np.isclose(g[:, 0], -40)
    surface = hull[~fixed[hull].all(axis=1)]
    return BodySetup(points=g, tets=tets, surface=surface, fixed=fixed, side=side, young_mpa=1e-3)


def mock_solver(X, fixed, *, increments=4, fail_at=None, augment=True):
    """A step solver for the spring body: Newton on the springs, the weight and the contact
    potentials (:class:`~regtrack.mechanics.potential.PlatePotential`) in ``increments``
    increments, each with its multipliers updated until the penetration and the friction
    lag meet the tolerances (``augment=False``: plain penalty, no updates).  The contact
    Hessian leaves out the plate edge's curvature term (:mod:`~regtrack.mechanics.potential`),
    so on the rounded edge Newton converges linearly (about a factor 3 per iteration here):
    up to 100 iterations reach the 1e-11 N residual the equilibrium checks rely on."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from regtrack.mechanics.potential import PlatePotential

    mask = np.repeat(~fixed, 3)

    def solve(u0, g0, g1, contribs, name, control):
        if fail_at == name:
            raise SolverDidNotConvergeError("mock: no convergence", load_fraction=0.5)
        u = u0.reshape(-1).copy()
        plates = [PlatePotential(c, u) for c in contribs]
        it = 0
        for t in np.linspace(0, 1, increments + 1)[1:]:
            for c in contribs:
                c.set_time(t)
            g = g0 + t * (g1 - g0)
            for _aug in range(30):
                for _ in range(100):
                    R = K_SPRING * u - np.tile(WEIGHT * g, len(X))
                    A = sp.diags(K_SPRING * np.ones(u.size)).tocsr()
                    for pl in plates:
                        e = pl.evaluate(u, hessian=True)
                        R += e.grad
                        A = A + e.hess.tocsr()
                    R[~mask] = 0
                    it += 1
                    if np.linalg.norm(R) < 1e-11:
                        break
                    du = np.zeros_like(u)
                    du[mask] = spla.spsolve(A[mask][:, mask].tocsc(), -R[mask])
                    u += du
                evs = [pl.evaluate(u, hessian=False) for pl in plates]
                if not augment or all(pl.max_violation(e) <= pl.c.config.penetration_tol_mm
                                      and pl.friction_error(e) <= pl.c.config.friction_tol
                                      for pl, e in zip(plates, evs)):
                    break
                for pl, e in zip(plates, evs):
                    pl.update(e, growth=1.0, slow_ratio=0.3, eps_max=np.inf, previous=None)
            for pl in plates:
                pl.commit(u)
        return u.reshape(-1, 3), {"iterations": it}
    return solve


def _run(protocol, body=None, **kw):
    body = body or _body()
    runner = ProtocolRunner(body, protocol, mock_solver(body.points, body.fixed, **kw),
                            config=ContactConfig(friction=0.1, chest_wall_contact=False))
    return runner.run(), runner


def test_shipped_protocols_parse():
    cc, mlo = shipped_protocol("cc"), shipped_protocol("mlo")
    assert [s.action for s in cc.steps] == ["gravity", "move_plate", "gravity", "move_plate"]
    assert cc.steps[-1].target_D == pytest.approx(0.38)
    assert mlo.steps[-1].target_D == pytest.approx(0.28)
    assert mlo.angle_deg == 45.0 and cc.view == "CC" and mlo.view == "MLO"
    # gravity is a patient-frame load: prone MRI gravity (LPS anterior) reversed, then
    # standing gravity (LPS inferior)
    assert cc.steps[0].frame == cc.steps[2].frame == "patient"
    np.testing.assert_allclose(cc.steps[0].direction, [0, 1, 0])
    np.testing.assert_allclose(cc.steps[2].direction, [0, 0, -1])


def test_patient_frame_gravity_does_not_turn_with_the_chest_wall():
    from regtrack.mechanics.protocol_run import gravity_direction
    from regtrack.model.geometry import make_frame

    cc = shipped_protocol("cc")
    # a patient-aligned model: the unloading is -x, standing gravity -y (model frame)
    np.testing.assert_allclose(gravity_direction(cc.steps[0], None), [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(gravity_direction(cc.steps[2], None), [0, -1, 0], atol=1e-12)
    # a right breast whose chest wall faces 20 deg laterally (towards -L): the model x is
    # that normal, and the prone gravity (LPS anterior) has a medial model component
    a = np.deg2rad(20.0)
    fr = make_frame(np.array([-np.sin(a), -np.cos(a), 0.0]), "R", np.zeros(3))
    d = gravity_direction(cc.steps[0], fr.axes)
    lps = fr.axes.T @ d  # back to LPS
    np.testing.assert_allclose(lps, [0, 1, 0], atol=1e-12)
    assert d[0] == pytest.approx(-np.cos(a)) and abs(d[2]) == pytest.approx(np.sin(a))
    np.testing.assert_allclose(fr.axes.T @ gravity_direction(cc.steps[2], fr.axes), [0, 0, -1],
                               atol=1e-12)


def test_cc_protocol_reaches_target_D_on_mock_body():
    res, runner = _run(shipped_protocol("cc"))
    assert res.complete
    last = res.steps[-1]
    # gap = (1 - D) T0 exactly, since D is defined on the plate gap
    assert last.D == pytest.approx(0.38, abs=1e-9)
    assert last.gap_mm == pytest.approx(0.62 * last.T0_mm, rel=1e-9)
    # gravity loads add up: -x (unloading) + -y (standing), 9.81 m/s^2 each
    np.testing.assert_allclose(last.gravity_ms2, [-9.81, -9.81, 0.0])
    assert last.max_penetration_mm <= ContactConfig().penetration_tol_mm + 1e-12
    # both plates press the body; the upper one pushes down (force on plate along +n)
    up, lo = last.contact["upper"], last.contact["lower"]
    assert up["normal_force_N"] > 0 and lo["normal_force_N"] > 0
    # equilibrium of the free nodes: force on both plates = -(springs - weight).  The
    # reported plate force is recomputed from the committed contact state (final normal,
    # slid stick points), not taken from the solve; with the C2 friction the two agree to
    # 7e-8 N on this 38 N load (1e-11 N with the piecewise-linear one), hence 1e-6 N
    body = runner.body
    free = ~body.fixed
    on_plates = np.add(up["force_N"], lo["force_N"])
    expected = -(K_SPRING * last.u[free].sum(axis=0) - free.sum() * WEIGHT * last.gravity_ms2)
    np.testing.assert_allclose(on_plates, expected, rtol=0, atol=1e-6)
    assert last.D_mean is not None and 0.0 < last.D_mean < 1.0


def test_mlo_plates_are_rotated_45_degrees():
    res, runner = _run(shipped_protocol("mlo"))
    n = runner.plates["lower"].plate.normal
    # right breast: medial = -z, n = cos45 y + sin45 m
    np.testing.assert_allclose(n, [0, np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(runner.plates["upper"].plate.normal, -n, atol=1e-12)
    assert res.steps[-1].D == pytest.approx(0.28, abs=1e-9)


def test_force_target_is_reached_within_tolerance():
    proto = apply_overrides(shipped_protocol("cc"), ProtocolOverrides(target_force_N=0.5))
    res, _ = _run(proto)
    f = res.steps[-1].contact["upper"]["normal_force_N"]
    assert f == pytest.approx(0.5, rel=0.02)


def test_gap_override_and_too_large_gap():
    proto = apply_overrides(shipped_protocol("cc"), ProtocolOverrides(target_gap_mm=20.0))
    res, _ = _run(proto)
    assert res.steps[-1].gap_mm == pytest.approx(20.0, abs=1e-9)
    with pytest.raises(ConfigError, match="uncompressed thickness"):
        _run(apply_overrides(shipped_protocol("cc"), ProtocolOverrides(target_gap_mm=500.0)))


def test_failure_keeps_last_converged_state_and_names_the_step():
    with pytest.raises(SolverDidNotConvergeError, match="step 3 'standing-gravity'") as ei:
        _run(shipped_protocol("cc"), fail_at="standing-gravity")
    partial = ei.value.last_converged
    assert [r.name for r in partial.steps] == ["gravity-unloading", "lower-plate-contact"]
    assert not partial.complete


def test_penetration_guard_rejects_soft_penalty():
    body = _body()
    runner = ProtocolRunner(body, shipped_protocol("cc"),
                            mock_solver(body.points, body.fixed, augment=False),
                            config=ContactConfig(penalty_factor=1e-3))
    with pytest.raises(ResultCheckError, match="inside a plate"):
        runner.run()


@pytest.mark.parametrize("table, match", [
    ({"view": "XX", "steps": [{"action": "hold"}]}, "view"),
    ({"view": "CC"}, "steps"),
    ({"view": "CC", "steps": [{"action": "gravity"}]}, "needs load"),
    ({"view": "CC", "steps": [{"action": "move_plate", "to": "degree"}]}, "target_D"),
    ({"view": "CC", "steps": [{"action": "jump"}]}, "action"),
    ({"view": "CC", "steps": [{"action": "hold", "colour": 1}]}, "colour"),
])
def test_bad_protocols_name_the_key(table, match):
    with pytest.raises(ConfigError, match=match):
        parse_protocol(table, where="p.toml")


def test_case_overrides_validation():
    with pytest.raises(ConfigError, match=r"\[protocol.CC\].*only one"):
        protocol_for_view("CC", {"target_D": 0.3, "target_gap_mm": 40.0})
    with pytest.raises(ConfigError, match="target_D"):
        protocol_for_view("MLO", {"target_D": 1.5})
    p = protocol_for_view("mlo", {"target_D": 0.3, "angle_deg": 50.0})
    assert p.steps[-1].target_D == 0.3 and p.angle_deg == 50.0


def test_plates_start_clear_of_a_thick_base_behind_their_edge():
    """The block's chest-wall base (x < -30, behind the plates' edge at -40 + 10) is made
    8 mm taller than the part over the plates: placed from the nodes over the plates only,
    the rounded edges would start inside it; every free surface node must start clearance_mm
    (2 mm) or more from both plates (the closest exactly 2 mm), so the plates back off."""
    from regtrack.mechanics.placement import make_plates

    b = _body()
    X = b.points.copy()
    base = X[:, 0] < -30.0
    X[base, 1] *= 1.0 + 8.0 / 15.0  # y in [-23, 23] behind the edge, [-15, 15] over the plates
    body = BodySetup(points=X, tets=b.tets, surface=b.surface, fixed=b.fixed, side="R",
                     young_mpa=1e-3)
    proto = apply_overrides(shipped_protocol("cc"), ProtocolOverrides(posterior_edge_mm=10.0))
    plates, _ = make_plates(body, proto, config=ContactConfig(chest_wall_contact=False))
    free = np.unique(body.surface)
    free = free[~body.fixed[free]]
    for pc in plates.values():
        assert pc.plate.query(X[free]).gap.min() == pytest.approx(2.0, abs=1e-6)
    over = free[X[free, 0] >= -30.0 + 10.0]  # beyond the edge's rounding: only the face counts
    assert plates["upper"].plate.query(X[over]).gap.min() > 2.0 + 1.0  # backed off for the base


@pytest.mark.parametrize("view", ["cc", "mlo"])
def test_shipped_plates_are_flat_in_front_of_the_chest_wall(view):
    """The shipped CC and MLO plates end their flat face at the chest-wall plane, so every
    point in front of the wall that touches a plate meets its face: gap = height over the
    face and normal = the face normal (a half-space).  With the edge 5 mm in front of the
    wall (radius 10 mm) the point 1 mm in front of the wall would meet the rounded edge,
    its normal tilted by asin(4/10) = 24 deg towards the wall."""
    from regtrack.mechanics.placement import make_plates

    body = _body()
    plates, _ = make_plates(body, shipped_protocol(view), config=ContactConfig())
    x_wall = body.points[:, 0].min()
    for pc in plates.values():
        pl = pc.plate
        # points 0.01 to 30 mm in front of the wall, on and 1 mm inside the face
        s = np.linspace(0.01, 30.0, 12)
        for depth in (0.0, -1.0):
            pts = np.array([pl.origin + depth * pl.normal + (x_wall + si - pl.origin @ pl.e1) * pl.e1
                            for si in s])
            q = pl.query(pts)
            np.testing.assert_allclose(q.normal, np.tile(pl.normal, (len(s), 1)), atol=1e-12)
            np.testing.assert_allclose(q.gap, depth, atol=1e-9)


@pytest.mark.parametrize("edge, radius, wall, refused", [
    (5.0, 10.0, True, True), (0.5, 10.0, True, True), (10.0, 10.0, True, True),
    (0.0, 10.0, True, False), (-20.0, 10.0, True, False), (10.5, 10.0, True, False),
    (20.0, 10.0, True, False), (5.0, 10.0, False, False)])
def test_a_rounded_edge_in_front_of_the_chest_wall_is_refused(edge, radius, wall, refused):
    """With the chest-wall contact on, a plate edge 0 < e <= r in front of the wall meets it
    at the acute angle 90 - asin(e / r) deg (0 at e = r: tangent to the wall) and pinches
    the base: make_plates refuses it naming the angle and the fix; e <= 0, e > r, or no wall
    contact are accepted."""
    from regtrack.mechanics.placement import make_plates

    proto = apply_overrides(shipped_protocol("cc"), ProtocolOverrides(posterior_edge_mm=edge,
                                                                      edge_radius_mm=radius))
    config = ContactConfig(chest_wall_contact=wall)
    if refused:
        angle = 90.0 - np.degrees(np.arcsin(edge / radius))
        with pytest.raises(ConfigError, match=rf"meets the wall at {angle:.0f} deg.*<= 0.*> 10"):
            make_plates(_body(), proto, config=config)
    else:
        plates, _ = make_plates(_body(), proto, config=config)
        assert plates["upper"].plate.s_range[0] == pytest.approx(-40.0 + edge)


def test_chest_wall_contact_pushes_tissue_back_in_front_of_the_wall():
    """``[contact] chest_wall_contact`` (on by default): a frictionless rigid wall at the
    chest-wall plane (x = -40 mm here) on every free node.  A node moved 0.1 mm behind the
    plane feels the penalty force eps_N * 0.1 mm * A, along +x only; the fixed nodes are no
    candidates; surface nodes carry their tributary surface area; the runner hands the wall to
    the solver with the plates."""
    from regtrack.mechanics.contact import tributary_areas
    from regtrack.mechanics.placement import chest_wall

    body = _body()
    assert chest_wall(body, ContactConfig(chest_wall_contact=False)) is None
    wall = chest_wall(body, ContactConfig())
    assert wall.mu == 0.0 and wall.name == "chest-wall"
    assert not body.fixed[wall.nodes].any()
    np.testing.assert_array_equal(wall.nodes, np.flatnonzero(~body.fixed))
    surface = np.unique(body.surface)
    on_surface = np.isin(wall.nodes, surface)
    np.testing.assert_allclose(wall.areas[on_surface],
                               tributary_areas(body.points, body.surface)[wall.nodes[on_surface]])
    assert np.all(wall.areas > 0)
    assert np.allclose(wall.plate.origin[0], -40.0) and np.allclose(wall.plate.normal, [1, 0, 0])
    i = int(np.flatnonzero(np.isclose(body.points[wall.nodes, 0], -35.0))[0])
    node = wall.nodes[i]
    u = np.zeros_like(body.points)
    f0, _ = wall.nodal_forces(u)
    assert not f0.any()  # nothing behind the wall: no force
    u[node, 0] = -5.1  # 0.1 mm behind the plane
    fc, _ = wall.nodal_forces(u)
    f = np.zeros_like(u)
    f[wall.nodes] = fc  # force on the body
    assert f[node] == pytest.approx([wall.eps_n * 0.1 * wall.areas[i], 0.0, 0.0], rel=1e-9)
    assert np.count_nonzero(np.abs(f).sum(axis=1)) == 1
    runner = ProtocolRunner(body, shipped_protocol("cc"), mock_solver(body.points, body.fixed))
    assert set(runner.contacts) == {"chest-wall"}  # the plates come in at the first plate step
    runner.run()
    assert set(runner.contacts) == {"lower", "upper", "chest-wall"}
    assert set(runner.plates) == {"lower", "upper"}


@pytest.mark.parametrize("view", ["cc", "mlo"])
def test_plates_stand_back_until_the_first_plate_step(view):
    """The breast hangs free until the protocol's first plate step, which places both plates
    ``clearance_mm`` from the shape it has then: the unloaded reference is the same for
    every view.  Known answer on the spring body: 10 g along +y moves every free node
    ``10 * 0.02 N / 0.05 N/mm = 4 mm``, twice the 2 mm clearance of plates placed around the
    reference shape (the CC's upper plate faces -y, the MLO's at 45 deg), with no plate
    force; the lower plate then touches the moved body and the upper one starts 2 mm from
    it."""
    steps = [{"name": "unload", "action": "gravity", "load": "u", "direction": [0.0, 1.0, 0.0],
              "factor": 10.0},
             {"name": "touch", "action": "move_plate", "plate": "lower", "to": "contact"}]
    table = {"name": view, "view": view.upper(), "steps": steps}
    res, runner = _run(parse_protocol(table, where="test"))
    body = _body()
    free = ~body.fixed
    np.testing.assert_allclose(res.steps[0].u[free], np.tile([0.0, 4.0, 0.0], (free.sum(), 1)),
                               atol=1e-9)
    assert res.steps[0].plates == {} and res.steps[0].gap_mm is None
    assert "lower" not in res.steps[0].contact
    x = body.points + res.steps[1].u
    for name, gap in (("lower", 0.0), ("upper", 2.0)):
        pc = runner.plates[name]
        assert pc.min_gap(res.steps[1].u) == pytest.approx(gap, abs=1e-6), name
        assert np.all(pc.plate.query(x[pc.nodes]).gap >= gap - 1e-6)


def test_the_result_does_not_depend_on_the_plates_clearance():
    """``clearance_mm`` only says where the plates wait before they move: the shipped CC on
    the spring body, with its unloading spread along the plates' normal (10 g along +y, 4 mm,
    more than either clearance), ends in the same state at 2 and 6 mm."""
    ends = []
    for clearance in (2.0, 6.0):
        proto = shipped_protocol("cc")
        steps = (replace(proto.steps[0], direction=[0.0, 1.0, 0.0], frame="model", factor=10.0),
                 *proto.steps[1:])
        proto = replace(proto, steps=steps, plates=replace(proto.plates, clearance_mm=clearance))
        res, _ = _run(proto)
        assert res.complete
        ends.append((res.steps[-1].u, res.steps[-1].gap_mm, res.steps[-1].T0_mm))
    np.testing.assert_allclose(ends[0][0], ends[1][0], atol=1e-8)
    assert ends[0][1:] == pytest.approx(ends[1][1:], abs=1e-8)


def test_behind_chest_wall_depth_is_measured_from_the_most_posterior_node():
    """Known answer: the plane is x = min X (here -40 mm); node depths x_cw - (X + u)_x."""
    from regtrack.mechanics.placement import behind_chest_wall

    X = np.array([[-40.0, 0, 0], [-35.0, 0, 0], [-30.0, 0, 0], [0.0, 0, 0]])
    fixed = np.array([True, False, False, False])
    u = np.zeros_like(X)
    assert behind_chest_wall(X, u, fixed) == (0.0, 0)
    u[1, 0], u[2, 0] = -12.5, -10.5  # 7.5 and 0.5 mm behind the plane
    assert behind_chest_wall(X, u, fixed) == (pytest.approx(7.5), 1)
    assert behind_chest_wall(X, u, fixed, over_mm=0.25)[1] == 2
    assert behind_chest_wall(X, u, np.zeros(4, bool)) == (None, None)  # no wall, no report


@pytest.mark.parametrize("factor, warned", [(1.0, False), (100.0, True)])
def test_a_step_reports_tissue_behind_the_chest_wall_and_warns_past_the_limit(factor, warned):
    """A gravity step along -x (posterior) pulls the mock body's free nodes back by
    u = W g / k: 0.4 mm at 9.81 m/s^2 (the first free plane, x = -35 mm, stays 4.6 mm in
    front of the wall), 40 mm at 100 g: the x = -35 plane ends 35 mm behind it (over the
    10 mm warning limit), and the planes x = -35 ... -5 mm more than 1 mm behind."""
    table = {"name": "pull", "view": "CC",
             "steps": [{"name": "pull", "action": "gravity", "load": "pull",
                        "direction": [-1.0, 0.0, 0.0], "factor": factor}]}
    res, runner = _run(parse_protocol(table, where="pull.toml"))
    rec = res.steps[-1]
    depth = WEIGHT * 9.81 * factor / K_SPRING - 5.0
    assert rec.behind_chest_wall_mm == pytest.approx(max(depth, 0.0), rel=1e-9)
    X = runner.body.points
    behind = ~runner.body.fixed & (X[:, 0] - WEIGHT * 9.81 * factor / K_SPRING < -41.0)
    assert rec.behind_chest_wall_nodes == int(behind.sum()) == (7 * 49 if warned else 0)
    assert bool(rec.warnings) is warned
    d = rec.to_dict()
    assert d["behind_chest_wall_mm"] == rec.behind_chest_wall_mm and d["warnings"] == rec.warnings
    if warned:
        assert "behind_wall_warn_mm" in rec.warnings[0] and "'pull'" in rec.warnings[0]


def test_force_balance_is_the_residual_resultant_over_the_free_nodes():
    """``force_balance``: the resultant of the residual over the free nodes against the
    largest load (the chest-wall reaction, the weight, each contribution's resultant).
    Three free nodes with residuals (0.1, 0, 0), (0.2, 0, 0), (0, 0.4, 0) N: resultant
    |(0.3, 0.4, 0)| = 0.5 N; the fixed node's 3 N reaction is smaller than the 10 N plate
    force, so the relative imbalance is 0.05: over a tolerance of 0.01, under 0.1."""
    from types import SimpleNamespace

    from regtrack.mechanics.problem import force_balance

    fixed = np.array([True, False, False, False])
    problem = SimpleNamespace(model=SimpleNamespace(fixed=fixed), fixed_dofs=np.arange(3), support=None, n_dofs=12,
                              body_weight=np.full(4, 0.05 / 9.81))  # 0.2 N at 1 g
    r = np.array([[0.0, 3.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.4, 0.0]])
    plate = SimpleNamespace(nodal_forces=lambda u: (np.array([[0.0, -6.0, 0.0],
                                                              [0.0, -4.0, 0.0]]), {}))
    u = np.zeros((4, 3))
    fb = force_balance(problem, u, r, np.array([0.0, -9.81, 0.0]), [plate], 0.01)
    assert fb["imbalance_N"] == pytest.approx(0.5, rel=1e-12)
    assert fb["load_N"] == pytest.approx(10.0, rel=1e-12)
    assert fb["relative"] == pytest.approx(0.05, rel=1e-12) and not fb["ok"]
    assert force_balance(problem, u, r, np.zeros(3), [plate], 0.1)["ok"]


def test_the_summary_reports_the_largest_force_imbalance_of_the_steps():
    """``force_imbalance_rel`` of the summary: the largest over the steps of the solver's
    ``force_balance`` (the step solver refuses a state above its tolerance)."""
    from regtrack.mechanics.run_view import summarise

    body = _body()
    inner = mock_solver(body.points, body.fixed)
    rels = iter([0.004, 0.001])

    def solve(*a, **k):
        u, st = inner(*a, **k)
        rel = next(rels)
        return u, dict(st, force_balance={"imbalance_N": rel * 40.8, "load_N": 40.8,
                                          "relative": rel, "tol": 5e-3, "ok": True})

    table = {"name": "sag", "view": "CC",
             "steps": [{"name": "sag", "action": "gravity", "load": "g",
                        "direction": [0.0, 0.0, -1.0], "factor": 1.0},
                       {"name": "hold", "action": "hold"}]}
    runner = ProtocolRunner(body, parse_protocol(table, where="sag.toml"), solve,
                            config=ContactConfig(friction=0.1))
    res = runner.run()
    assert res.complete and not any("balance" in w for s in res.steps for w in s.warnings)
    assert summarise(res)["force_imbalance_rel"] == 0.004


def test_biopsy_with_both_plates_moved_is_a_protocol_file():
    """Issue 55's "lateral fixed, medial moved, or both": a biopsy protocol whose lateral
    plate, after contact, also travels 3 mm towards the breast (``to = "position"``) before
    the medial one closes to D = 26 %.  Both plates end where the steps put them: the
    lateral plate's face 3 mm further along its normal, the gap (1 - D) T0 (by hand)."""
    table = {"name": "biopsy-both", "view": "BIOPSY", "angle_deg": 90.0,
             "plates": {"posterior_edge_mm": 5.0},
             "steps": [{"action": "move_plate", "plate": "lower", "to": "contact"},
                       {"action": "move_plate", "plate": "upper", "to": "contact"},
                       {"action": "move_plate", "plate": "lower", "to": "position",
                        "distance_mm": 3.0},
                       {"action": "move_plate", "plate": "upper", "to": "degree",
                        "target_D": 0.26}]}
    res, runner = _run(parse_protocol(table, where="test"))
    assert res.complete
    n = runner.plates["lower"].plate.normal
    touched, moved = (np.asarray(res.steps[i].plates["lower"]["origin_mm"]) for i in (1, 2))
    assert (moved - touched) @ n == pytest.approx(3.0, abs=1e-9)
    np.testing.assert_allclose(res.steps[3].plates["lower"]["origin_mm"], moved)
    assert res.steps[-1].gap_mm == pytest.approx(0.74 * res.steps[-1].T0_mm, rel=1e-9)
