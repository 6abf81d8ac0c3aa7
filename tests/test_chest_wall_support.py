"""The sliding chest wall (regtrack.mechanics.support): the base held normal to the wall
and tangentially by a layer of the tissue's shear stiffness ``mu / h`` per unit area."""

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


def test_the_layer_is_part_of_the_potential():
    """The layer's energy, gradient and stiffness enter ``Pi`` consistently: the residual
    is the derivative of the potential, and the tangent that of the residual (central
    differences, 1e-6 and 1e-5 relative), at a random state in which the base has slid
    (plain P1, whose tangent is the assembled matrix itself)."""
    _, prob = _block(5.0, divisions=(2, 2, 2), formulation="p1")
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
