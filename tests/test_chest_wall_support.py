"""The chest-wall support (regtrack.mechanics.support): the base held normal to the wall
and tangentially by a layer of the tissue's shear stiffness ``mu / h`` per unit area while
the breast hangs free, and following the plates along their normal once they hold it."""

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


def test_following_the_plates_frees_the_base_along_their_normal_and_holds_it_across():
    """``WallSupport.following(n)``: no energy for a base moved along ``n`` projected on
    the wall (an MLO-like normal at 50 deg, with a component along the wall's normal that
    the projection drops), ``1/2 F_h sum k_i s^2`` for a move ``s`` across it, and the layer
    unchanged for a normal along the wall's own."""
    from regtrack.mechanics.support import HELD_FACTOR

    model, prob = _block(5.0)
    layer = prob.support
    a = np.radians(50.0)
    n = np.array([0.3, np.cos(a), np.sin(a)])
    follow = layer.following(n)
    base = model.fixed
    along = np.zeros_like(prob.X)
    along[base, 1:] = 0.7 * np.array([np.cos(a), np.sin(a)])
    assert follow.energy(along) == pytest.approx(0.0, abs=1e-12 * layer.energy(along))
    assert np.abs(follow.gradient(along)).max() < 1e-12 * np.abs(layer.gradient(along)).max()
    across = np.zeros_like(prob.X)
    across[base, 1:] = 0.7 * np.array([-np.sin(a), np.cos(a)])
    assert follow.energy(across) == pytest.approx(0.5 * HELD_FACTOR * layer.k.sum() * 0.49, rel=1e-12)
    assert layer.energy(across) == pytest.approx(0.5 * layer.k.sum() * 0.49, rel=1e-12)
    assert layer.following([1.0, 0.0, 0.0]) is layer


@pytest.mark.parametrize("s", [0.0, 0.25, 0.5, 1.0])
def test_a_partial_release_ramps_the_stiffness_along_the_normal_to_zero(s):
    """``following(n, released=s)``: the base's stiffness along the plates' normal is the
    layer's times ``1 - s`` and across it the layer's times ``1 - s + s F_h`` (energies of
    a unit move, exact to rounding); ``s = 0`` is the layer, ``s = 1`` the full release."""
    from regtrack.mechanics.support import HELD_FACTOR

    model, prob = _block(5.0)
    layer = prob.support
    a = np.radians(40.0)
    part = layer.following([0.0, np.cos(a), np.sin(a)], released=s)
    base = model.fixed
    along, across = np.zeros_like(prob.X), np.zeros_like(prob.X)
    along[base, 1:] = [np.cos(a), np.sin(a)]
    across[base, 1:] = [-np.sin(a), np.cos(a)]
    full = 0.5 * layer.k.sum()
    assert part.energy(along) == pytest.approx((1 - s) * full, rel=1e-12, abs=1e-12 * full)
    assert part.energy(across) == pytest.approx((1 - s + s * HELD_FACTOR) * full, rel=1e-12)


@pytest.mark.parametrize("follow", [False, True])
def test_the_layer_is_part_of_the_potential(follow):
    """The support's energy, gradient and stiffness enter ``Pi`` consistently: the residual
    is the derivative of the potential, and the tangent that of the residual (central
    differences, 1e-6 and 1e-5 relative), at a random state in which the base has slid
    (plain P1, whose tangent is the assembled matrix itself); on the layer and following
    an oblique plate normal (a full 2 x 2 block per node)."""
    _, prob = _block(5.0, divisions=(2, 2, 2), formulation="p1")
    if follow:
        prob.support = prob.support.following([0.0, np.cos(0.8), np.sin(0.8)])
    m = Minimiser(prob, SolverOptions())
    rng = np.random.default_rng(3)
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
def test_T0_is_measured_on_the_breast_settled_with_its_base_free():
    """At the upper plate's first touch the base is freed along the plates' normal, the
    breast settles on the lower plate, and the plate touches it again, so that ``T0`` is
    the extent above the lower plate of the breast as it is then compressed.  On the
    phantom's MLO (coarse, ~1.8k nodes): a run that stops at that touch has ``T0`` as its
    gap (to 1e-9 mm) and its surface's highest point there (within the contact tolerance,
    0.05 mm), the upper plate carries no force there (below 1e-3 of the breast's weight),
    and the breast settled lower than it stood on the layer (by more than 1 mm)."""
    from dataclasses import replace
    from pathlib import Path

    from regtrack.case import load_case
    from regtrack.mechanics.protocol import shipped_protocol
    from regtrack.mechanics.run_view import run_protocol_on_model
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
    standing, settled = res_t.steps[-2], res_t.steps[-1]

    def extent(rec):
        low = rec.plates["lower"]
        return float(((model.points + rec.u - low["origin_mm"]) @ np.asarray(low["normal"])).max())

    weight = case.config("mechanics").density_kg_m3 * model.tet_volumes().sum() * 1e-9 * 9.81
    assert res_f.steps[-1].T0_mm == pytest.approx(settled.gap_mm, abs=1e-9)
    assert extent(settled) == pytest.approx(settled.gap_mm, abs=0.05)
    assert abs(settled.contact["upper"]["normal_force_N"]) < 1e-3 * weight
    assert extent(settled) < extent(standing) - 1.0
