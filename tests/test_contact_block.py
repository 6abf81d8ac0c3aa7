"""Friction block: a soft block pressed onto a rigid plate, then sheared (issue 5).

A 10 x 10 x 5 mm neo-Hookean block (c1 = 1 kPa, nu = 0.3, plain P1, no skin) rests on
the plate z = 0.  Its top face is driven: first down by 0.5 mm (step 1), then sideways
by 2 mm (step 2).  Coulomb's law says the bottom sticks while the shear force T is
below mu*N and slides with T = mu*N once every contact node slips.  The friction
potential makes T = mu*pbar node by node, with the lagged pressure pbar iterated to within
``friction_tol`` (0.1 %) of the current one at the end of every step, so the 2 % acceptance
tolerance only has to absorb that and the solver's residual tolerance.  The shear is run
as 10 steps of one increment each, so that every state it reports has a converged lag.
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.mechanics.contact import ContactConfig, PlateContact, tributary_areas
from regtrack.mechanics.meshes import box_model
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.plates import RigidPlate
from regtrack.mechanics.problem import build_problem

OPTS = SolverOptions(force_tol=1e-8, balance_tol=1e-6)


def _block_on_plate(mu: float):
    """(problem, reference points, plate contact of the bottom face, top nodes, their dofs)."""
    model = box_model((10.0, 10.0, 5.0), (4, 4, 2))
    cfg = MechanicsConfig(tissue_c1_kpa=1.0, nu=0.3, formulation="p1", skin_enabled=False)
    prob = build_problem(model, cfg)
    X = model.points
    bottom = model.skin[np.all(np.isclose(X[model.skin][:, :, 2], 0.0), axis=1)]
    nodes = np.unique(bottom)
    plate = RigidPlate(name="lower", origin=(0, 0, 0), normal=(0, 0, 1), e1=(1, 0, 0))
    c = PlateContact(plate, X, nodes, tributary_areas(X, bottom)[nodes],
                     config=ContactConfig(friction=mu, penetration_tol_mm=1e-3), penalty=0.01)
    top = np.flatnonzero(np.isclose(X[:, 2], 5.0))
    return prob, X, c, top, (3 * top[:, None] + np.arange(3)).ravel()


def _press_and_shear(mu: float, shear_mm: float = 2.0, steps: int = 10):
    """Press the block 0.5 mm (10 increments), then shear its top by ``shear_mm`` in
    ``steps`` steps; the plate's report after each shear step."""
    prob, X, c, top, dofs = _block_on_plate(mu)

    def drive(sx, dz):
        return lambda t: (dofs, np.tile([sx(t), 0.0, dz(t)], len(top)))

    u, _, _ = minimise_step(prob, np.zeros_like(X), dirichlet=drive(lambda t: 0.0, lambda t: -0.5 * t),
                            contacts=[c], n_increments=10, options=OPTS, step_name="press")
    reps = []
    for k in range(steps):
        a, b = shear_mm * k / steps, shear_mm * (k + 1) / steps
        u, _, _ = minimise_step(prob, u, dirichlet=drive(lambda t: a + (b - a) * t, lambda t: -0.5),
                                contacts=[c], n_increments=1, options=OPTS, step_name="shear")
        reps.append(c.report(u))
    return reps


def test_block_sticks_below_and_slides_at_mu_n():
    mu = 0.1
    reps = _press_and_shear(mu)
    first, last = reps[0], reps[-1]
    # start of the shear: part of the contact still sticks, T below mu N
    assert first["n_slip"] < first["n_active"]
    assert first["tangential_force_N"] < mu * first["normal_force_N"]
    # sliding: every contact node slips and T = mu N within 2 %
    assert last["n_slip"] == last["n_active"] > 0
    assert last["tangential_force_N"] == pytest.approx(mu * last["normal_force_N"], rel=0.02)
    # T never exceeds mu N during the shear (the lagged bound is accepted within
    # friction_tol = 0.1 % of the current pressure's)
    tol = ContactConfig().friction_tol
    for r in reps:
        assert r["tangential_force_N"] <= mu * r["normal_force_N"] * (1 + tol)
    # the force resists the motion (+x shear of the top -> the plate is dragged along +x)
    assert last["force_N"][0] > 0


def test_frictionless_block_transmits_no_shear():
    reps0 = _press_and_shear(0.0, shear_mm=0.5)
    reps1 = _press_and_shear(0.1, shear_mm=0.5)
    assert all(r["tangential_force_N"] < 1e-9 for r in reps0)
    assert reps1[-1]["tangential_force_N"] > 0.5 * 0.1 * reps1[-1]["normal_force_N"]


@pytest.mark.parametrize("band, share", [(0.0, 0.0), (4.0, None), (100.0, 1.0)])
def test_edge_band_force_is_the_force_of_the_nodes_near_the_plate_edge(band, share):
    """``edge_normal_force_N``: the normal force of the nodes whose reference position lies
    within ``edge_band_mm`` in front of the plate's chest-wall edge (here s = -1 mm, 1 mm
    behind the block's x = 0 face).  The block is pressed 0.5 mm; with band 4 mm the
    nodes at x = 0 and 2.5 mm count (two of the five node columns), so the share is that
    of their tributary areas: between 0.2 and 0.5 of the force (the pressure is not
    uniform under a frictional press)."""
    model = box_model((10.0, 10.0, 5.0), (4, 4, 2))
    prob = build_problem(model, MechanicsConfig(tissue_c1_kpa=1.0, nu=0.3, formulation="p1",
                                                skin_enabled=False))
    X = model.points
    bottom = model.skin[np.all(np.isclose(X[model.skin][:, :, 2], 0.0), axis=1)]
    nodes = np.unique(bottom)
    plate = RigidPlate(name="lower", origin=(0, 0, 0), normal=(0, 0, 1), e1=(1, 0, 0),
                       s_range=(-1.0, np.inf))
    c = PlateContact(plate, X, nodes, tributary_areas(X, bottom)[nodes],
                     config=ContactConfig(friction=0.1, penetration_tol_mm=1e-3, edge_band_mm=band),
                     penalty=0.01)
    top = np.flatnonzero(np.isclose(X[:, 2], 5.0))
    dofs = (3 * top[:, None] + np.arange(3)).ravel()
    u, _, _ = minimise_step(prob, np.zeros_like(X), contacts=[c], n_increments=10, options=OPTS,
                            step_name="press",
                            dirichlet=lambda t: (dofs, np.tile([0.0, 0.0, -0.5 * t], len(top))))
    rep = c.report(u)
    f, _ = c.nodal_forces(u)
    near = X[nodes, 0] < 2.6
    assert rep["normal_force_N"] > 0
    if share is None:
        assert rep["edge_normal_force_N"] == pytest.approx(float(f[near, 2].sum()), rel=1e-9)
        assert 0.2 < rep["edge_normal_force_N"] / rep["normal_force_N"] < 0.5
    else:
        assert rep["edge_normal_force_N"] == pytest.approx(share * rep["normal_force_N"], rel=1e-9,
                                                           abs=1e-12)
