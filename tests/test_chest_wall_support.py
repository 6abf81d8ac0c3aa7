"""The chest-wall support (regtrack.mechanics.support): the base held normal to the wall
and tangentially on a layer of the tissue's shear stiffness ``mu / h`` per unit area,
whose far side (the body beyond the cut) is at rest while the breast hangs free and is
squeezed with the plates once they hold it."""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.mechanics.meshes import box_model
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.newton import Minimiser
from regtrack.mechanics.problem import body_force, build_problem, chest_wall_reaction

C1_KPA = 1.0
RHO = 1000.0


def _block(layer_mm: float, divisions=(3, 3, 3), formulation="p1-anp"):
    """A 10 mm cube whose x = 0 face is the chest wall."""
    model = box_model((10.0, 10.0, 10.0), divisions)
    model.fixed[:] = np.isclose(model.points[:, 0], 0.0)
    cfg = MechanicsConfig(tissue_c1_kpa=C1_KPA, nu=0.45, skin_enabled=False, density_kg_m3=RHO,
                          formulation=formulation)
    return model, build_problem(model, cfg, wall_layer_mm=layer_mm)


def _hang(prob, g):
    u, _, r = minimise_step(prob, np.zeros_like(prob.X), gravity=lambda t: t * np.asarray(g, float),
                            n_increments=2, options=SolverOptions())
    return u, r


def test_the_layer_carries_the_weight_at_its_shear_stiffness():
    """A cube on the wall under gravity along the wall (y, 50 g to load the layer well):
    the layer's springs ``k_i = mu A_i / h`` carry the whole weight ``W``, so the
    area-weighted mean tangential displacement of the base is exactly ``W h / (mu A)``
    whatever the cube's deformation (global equilibrium; the tolerance is the solver's
    force tolerance), the base keeps ``u_x = 0``, and the chest-wall reaction is ``-W``.
    With h = 100 mm the layer is ten times softer than the 10 mm cube in shear, so the
    base translates nearly as a whole (spread below 10 % of the mean)."""
    h, g = 100.0, 50 * 9.81
    model, prob = _block(h)
    u, r = _hang(prob, (0.0, -g, 0.0))
    base = model.fixed
    from regtrack.mechanics.contact import tributary_areas
    from regtrack.mechanics.support import wall_face

    area = tributary_areas(model.points, wall_face(model.points, model.tets, base))[base]
    assert area.sum() == pytest.approx(100.0, rel=1e-12)
    W = RHO * 1e3 * g * 1e-9  # N: 1000 mm^3 at rho (kg/m^3) and g (m/s^2)
    mu = 2 * C1_KPA * 1e-3
    expected = -W * h / (mu * 100.0)
    mean = float(area @ u[base, 1]) / area.sum()
    assert mean == pytest.approx(expected, rel=1e-4)
    assert np.abs(u[base, 0]).max() == 0.0
    assert np.ptp(u[base, 1]) < 0.1 * abs(expected)
    react = chest_wall_reaction(prob, u, r)
    assert react == pytest.approx([0.0, W, 0.0], abs=1e-4 * W)


def test_a_thin_layer_tends_to_the_clamped_wall_and_zero_is_clamped():
    """As ``h -> 0`` the layer's stiffness grows as ``1 / h`` and the base displacement
    falls in proportion (1e-3 mm gives a base 1e4 times stiffer than the 10 mm cube:
    the tip deflection within 0.5 % of the clamped one); ``h = 0`` clamps the base (every
    dof of the chest-wall nodes held, no layer)."""
    g = (0.0, -50 * 9.81, 0.0)
    _, clamped = _block(0.0)
    assert clamped.support is None and len(clamped.fixed_dofs) == 3 * int(clamped.model.fixed.sum())
    uc, _ = _hang(clamped, g)
    _, thin = _block(1e-3)
    assert len(thin.fixed_dofs) == int(thin.model.fixed.sum())
    ut, _ = _hang(thin, g)
    tip = np.isclose(clamped.X[:, 0], 10.0)
    assert ut[tip, 1].mean() == pytest.approx(uc[tip, 1].mean(), rel=5e-3)
    base = clamped.model.fixed
    assert np.abs(ut[base]).max() < 1e-3 * np.abs(uc[tip]).max()


def test_the_layer_is_stretched_by_the_base_moving_away_from_the_body():
    """``WallSupport.moved(b)``: the body beyond the layer displaced by ``b``; the energy
    is ``1/2 sum_i k_i |u_i - b_i|^2`` over the in-wall components (exact to rounding):
    nothing for a base that moves with the body (any in-wall direction, and whatever its
    ``x`` component, which the wall holds), the layer's own for a base moved ``d`` from
    it, and its gradient minus the springs' force ``-k (u - b)``."""
    model, prob = _block(5.0)
    layer = prob.support
    base = model.fixed
    a = np.radians(50.0)
    body = np.zeros_like(prob.X)
    body[base] = [0.3, 4.0 * np.cos(a), 4.0 * np.sin(a)]
    moved = layer.moved(body)
    assert moved.energy(body) == pytest.approx(0.0, abs=1e-12 * layer.energy(body))
    assert np.abs(moved.gradient(body)).max() < 1e-12 * np.abs(layer.gradient(body)).max()
    d = np.zeros_like(prob.X)
    d[base, 1:] = 0.7 * np.array([-np.sin(a), np.cos(a)])
    assert moved.energy(body + d) == pytest.approx(layer.energy(d), rel=1e-12)
    assert moved.energy(body + d) == pytest.approx(0.5 * layer.k.sum() * 0.49, rel=1e-12)
    g = moved.gradient(body + d).reshape(-1, 3)
    assert np.allclose(g[base, 1:], layer.k[:, None] * d[base, 1:], rtol=1e-12, atol=0.0)
    assert np.all(g[~base] == 0.0) and np.all(g[:, 0] == 0.0)


def test_squeeze_weights_place_each_point_between_the_plates():
    """``squeeze_weights``: the height above the lower plate's face along the normal over
    the gap, clipped to [0, 1] (an oblique MLO-like normal; exact values)."""
    from regtrack.mechanics.support import squeeze_weights

    n = np.array([0.0, np.cos(0.7), np.sin(0.7)])
    lower = np.array([1.0, -2.0, 3.0])
    heights = np.array([-5.0, 0.0, 10.0, 25.0, 40.0, 60.0])
    tangent = np.array([0.0, -np.sin(0.7), np.cos(0.7)])
    x = lower + heights[:, None] * n + 7.0 * tangent + np.array([3.0, 0.0, 0.0])
    w = squeeze_weights(x, lower, n, 40.0)
    assert w == pytest.approx([0.0, 0.0, 0.25, 0.625, 1.0, 1.0], abs=1e-12)


@pytest.mark.parametrize("moved", [False, True])
def test_the_layer_is_part_of_the_potential(moved):
    """The support's energy, gradient and stiffness enter ``Pi`` consistently: the residual
    is the derivative of the potential, and the tangent that of the residual (central
    differences, 1e-6 and 1e-5 relative), at a random state in which the base has slid
    (plain P1, whose tangent is the assembled matrix itself); with the body at rest and
    displaced."""
    _, prob = _block(5.0, divisions=(2, 2, 2), formulation="p1")
    rng = np.random.default_rng(3)
    if moved:
        prob.support = prob.support.moved(rng.standard_normal(prob.X.shape))
    m = Minimiser(prob, SolverOptions())
    u = 0.2 * rng.standard_normal(prob.X.shape)
    u[prob.model.fixed, 0] = 0.0
    fext = body_force(prob, np.array([0.0, -9.81, 0.0]))
    s = m.state(u, fext, [], hessian=True)
    d = np.zeros_like(u)
    d[prob.model.fixed, 1:] = rng.standard_normal((int(prob.model.fixed.sum()), 2))
    eps = 1e-5
    fd = (m.state(u + eps * d, fext, [], hessian=False).energy
          - m.state(u - eps * d, fext, [], hessian=False).energy) / (2 * eps)
    assert fd == pytest.approx(float(s.R @ d.reshape(-1)), rel=1e-6)
    # the Hessian's layer part: the change of the residual along d
    dR = (m.state(u + eps * d, fext, [], hessian=False).R - m.state(u - eps * d, fext, [], hessian=False).R) / (2 * eps)
    K = prob.pattern.matrix(s.ev.data)
    assert np.allclose(K @ d.reshape(-1), dR, rtol=1e-5, atol=1e-9 * np.abs(dR).max())


@pytest.mark.slow
def test_T0_is_measured_at_the_touch_and_the_base_is_squeezed_with_the_plates():
    """At the upper plate's first touch ``T0`` is the plate gap, the breast's extent above
    the lower plate (within the contact tolerance, 0.05 mm) with no force on the upper
    plate (below 1e-3 of the breast's weight); from there the body beyond the chest wall
    is squeezed with the plates, so the base follows them: on the phantom's MLO (coarse,
    ~1.8k nodes) compressed by D = 28 %, the base nodes between the plates move along the
    normal by their share ``w`` of the plate travel: on average to within 5 % of the
    travel (the layer's mean stretch; 1.7 % measured), each in step with its ``w``
    (correlation above 0.95; 0.99 measured), single nodes departing further where the
    compressed tissue in front of the wall drags the layer (up to 13 % of the travel)."""
    from dataclasses import replace
    from pathlib import Path

    from regtrack.case import load_case
    from regtrack.mechanics.protocol import shipped_protocol
    from regtrack.mechanics.run_view import run_protocol_on_model
    from regtrack.mechanics.support import squeeze_weights
    from tests._models import coarse_model

    phantom = Path(__file__).resolve().parents[1] / "sample_cases" / "phantom01"
    case = load_case(phantom, deep=False)
    model = coarse_model(phantom)
    full = shipped_protocol("mlo")
    touch = replace(full, steps=(*full.steps[:-1], replace(full.steps[-1], to="contact",
                                                            target_D=None)))
    cfg = {"mechanics": case.config("mechanics"), "contact": case.config("contact")}
    res_t, _ = run_protocol_on_model(model, touch, **cfg)
    res_f, _ = run_protocol_on_model(model, full, **cfg)
    assert res_t.complete and res_f.complete
    at_touch, done = res_t.steps[-1], res_f.steps[-1]
    low = at_touch.plates["lower"]
    n = np.asarray(low["normal"])
    x_touch = model.points + at_touch.u
    weight = case.config("mechanics").density_kg_m3 * model.tet_volumes().sum() * 1e-9 * 9.81
    assert done.T0_mm == pytest.approx(at_touch.gap_mm, abs=1e-9)
    assert float(((x_touch - low["origin_mm"]) @ n).max()) == pytest.approx(at_touch.gap_mm, abs=0.05)
    assert abs(at_touch.contact["upper"]["normal_force_N"]) < 1e-3 * weight
    travel = at_touch.gap_mm - done.gap_mm
    assert done.D == pytest.approx(0.28, abs=1e-9)
    base = model.fixed
    w = squeeze_weights(x_touch[base], low["origin_mm"], n, at_touch.gap_mm)
    moved = -(done.u[base] - at_touch.u[base]) @ n  # along the normal, towards the lower plate
    between = (w > 0) & (w < 1)
    assert between.sum() > 10
    assert abs(np.mean(moved[between] - w[between] * travel)) < 0.05 * travel
    assert np.corrcoef(moved[between], w[between])[0, 1] > 0.95
