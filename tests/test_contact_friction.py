"""Plate contact state and reports (regtrack.mechanics.contact) with the solver mocked out.

* tributary areas and the automatic penalty rule; bad ``[contact]`` settings are named;
* the reported contact forces are those of the potential the solver minimises (its
  negative gradient) at the committed state, to round-off;
* node-wise penalty growth of the multiplier updates (:meth:`.potential.PlatePotential.update`);
* the relaxed multiplier update keeps Uzawa's fixed point and damps its overshoot.
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.config import parse_section
from regtrack.mechanics.contact import (ContactConfig, PlateContact, automatic_penalty,
                                        tributary_areas)
from regtrack.mechanics.plates import RigidPlate
from regtrack.mechanics.potential import PlatePotential


def _contact(X, *, mu=0.3, eps=2.0, areas=None):
    plate = RigidPlate(name="upper", origin=(0, 0, 0), normal=(0, 0, 1), e1=(1, 0, 0),
                       s_range=(0.0, np.inf), edge_radius=3.0)
    a = np.full(len(X), 2.0) if areas is None else areas
    return PlateContact(plate, X, np.arange(len(X)), a, config=ContactConfig(friction=mu), penalty=eps)


def test_tributary_area_sums_to_surface_area():
    pts = np.array([[0, 0, 0], [2, 0, 0], [2, 3, 0], [0, 3, 0]], float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    a = tributary_areas(pts, tris)
    assert a.sum() == pytest.approx(6.0)
    np.testing.assert_allclose(a, [2.0, 1.0, 2.0, 1.0])


def test_automatic_penalty_rule_and_config_validation():
    cfg = ContactConfig()
    assert automatic_penalty(cfg, young_mpa=6e-3, h_mm=3.0) == pytest.approx(20 * 6e-3 / 3.0)
    _, problems, warnings = parse_section(ContactConfig, {"friction": -0.1, "frction": 0.1,
                                                          "friction_bound": "current"},
                                          where="case.toml [contact]")
    assert any("friction" in p and "-0.1" in p for p in problems)
    assert any("did you mean 'friction'" in w for w in warnings)
    # an option of the former residual Newton solver is an unknown key now
    assert any("unknown key 'friction_bound'" in w for w in warnings)


def test_reported_forces_are_the_negative_gradient_of_the_potential():
    """Nodes off contact, pressed and sticking, pressed and sliding, and on the rounded
    edge: after a commit, :meth:`PlateContact.nodal_forces` (the report's forces) equals
    ``-dPi/dx`` of the potential at the same state (the normal of the current position,
    the committed multipliers, stick points and bound), to 1e-12 relative."""
    X = np.array([[10.0, 0.0, 1.0],     # off contact (gap 1 mm)
                  [10.0, 0.0, -0.2],    # pressed, sticks
                  [20.0, 5.0, -0.3],    # pressed, slides (stick point far away)
                  [-1.0, 2.0, -2.5]])   # on the rounded edge
    c = _contact(X)
    u = np.zeros_like(X)
    pl = PlatePotential(c, u)
    e = pl.evaluate(u, hessian=False)
    pl.update(e, growth=1.0, slow_ratio=0.3, eps_max=1.0, previous=None)  # lam = pbar = p
    pl.anchor_local[2] += [3.0, -1.0, 0.0]
    pl.commit(u)
    f, st = c.nodal_forces(u)
    pl = PlatePotential(c, u)  # the committed state, normals at u
    g = pl.evaluate(u, hessian=False).grad.reshape(-1, 3)
    np.testing.assert_allclose(f, -g, rtol=1e-12, atol=1e-12 * np.abs(g).max())
    assert st["active"].tolist() == [False, True, True, True]
    t = f[2] - (f[2] @ [0, 0, 1]) * np.array([0, 0, 1])  # sliding: |t| = mu A pbar (lagged)
    assert np.linalg.norm(t) == pytest.approx(0.3 * 2.0 * c.get_state()["pconv"][2], rel=1e-12)


def test_slow_uzawa_nodes_get_a_larger_penalty():
    """Node-wise penalty growth (contact.py docstring): a node whose violation did not fall
    below ``slow_uzawa_ratio`` of the previous one between two multiplier updates gets
    ``penalty_growth`` times its penalty, at most ``penalty_growth_max`` times the
    automatic one; nodes within the tolerance, converging, or off contact keep it.  The
    mock "body" does not move (the stiff-support limit, where plain Uzawa stalls)."""
    X = np.array([[10.0, 0.0, -0.5],    # penetrating 0.5 mm, and stays there
                  [12.0, 0.0, -0.01],   # within penetration_tol (0.02 mm), but slow: grows
                  [14.0, 0.0, 2.0]])    # off contact
    c = _contact(X, mu=0.0)
    cfg = c.config
    u = np.zeros_like(X)
    pl = PlatePotential(c, u)

    def update(u, previous):
        return pl.update(pl.evaluate(u, hessian=False), growth=cfg.penalty_growth,
                         slow_ratio=cfg.slow_uzawa_ratio,
                         eps_max=cfg.penalty_growth_max * c.eps_n, previous=previous)

    v = update(u, None)  # no history: no growth
    np.testing.assert_array_equal(pl.eps, [2.0, 2.0, 2.0])
    v = update(u, v)  # violations unchanged (ratio 1 > 0.3): both pressed nodes grow
    np.testing.assert_array_equal(pl.eps, [8.0, 8.0, 2.0])
    u1 = u.copy()
    u1[0, 2] = 0.49  # node 0 now 0.01 mm deep (ratio 0.02 < 0.3): keeps its penalty
    update(u1, v)
    assert pl.eps[0] == 8.0
    for _ in range(10):
        v = update(u, v)
    assert pl.eps[0] == pytest.approx(2.0 * 256)  # capped


def test_relaxed_update_keeps_the_fixed_point_and_damps_an_overshooting_response():
    """:meth:`PlatePotential.update`: the first update of an increment is Uzawa's ``lam =
    pbar = p``, and a state with ``p = lam = pbar`` (constraint and Coulomb's law
    consistent) is left unchanged.  A mock response whose gap grows with the multiplier,
    ``g = g0 + c lam`` with ``eps c = 2.5`` (a solve that overshoots, as a node snapping
    around a plate's edge does), makes the plain update oscillate with growing amplitude
    (factor ``1 - eps c = -1.5`` per update); Aitken's relaxation estimates ``omega = 1 /
    (1 - mu) = 0.4`` from two updates, which for this linear map lands on the fixed point
    ``lam* = -g0 / c`` (gap closed) at the next update, to round-off."""
    X = np.array([[10.0, 0.0, -0.1]])
    c = _contact(X, mu=0.3, eps=2.0)
    u = np.zeros_like(X)
    pl = PlatePotential(c, u)
    pl.lam[:] = pl.pbar[:] = 0.2  # p = lam - eps g = 0.2 + 2 * 0.1 = 0.4
    v = pl.update(pl.evaluate(u, hessian=False), growth=1.0, slow_ratio=0.3, eps_max=2.0, previous=None)
    assert pl.lam[0] == pytest.approx(0.4, rel=1e-12) and pl.pbar[0] == pytest.approx(0.4, rel=1e-12)
    u1 = u.copy()
    u1[0, 2] = 0.1  # gap closed: p = lam, a fixed point
    pl.update(pl.evaluate(u1, hessian=False), growth=1.0, slow_ratio=0.3, eps_max=2.0, previous=v)
    np.testing.assert_allclose([pl.lam[0], pl.pbar[0]], [0.4, 0.4], rtol=1e-14)

    g0, slope = -0.5, 1.25  # gap g = g0 + slope * lam (mm, MPa); eps * slope = 2.5
    star = -g0 / slope

    def mock_solve(lam):  # the state at multiplier lam: the mock gap, p = lam - eps g
        pl.lam[:] = lam
        u2 = u.copy()
        u2[0, 2] = 0.1 + g0 + slope * lam
        return pl.evaluate(u2, hessian=False)

    pl = PlatePotential(c, u)
    plain = [0.3]
    for _ in range(6):  # lam <- p = 1 - 1.5 lam: 0.55, 0.175, 0.74, then a 0 <-> 1 cycle
        plain.append(float(mock_solve(plain[-1]).pressure[0]))
    assert abs(plain[-1] - star) > abs(plain[1] - star)  # Uzawa: growing oscillation
    assert plain[-2:] == [pytest.approx(1.0), 0.0]
    pl.lam[:] = pl.pbar[:] = 0.3
    v = None
    for _ in range(3):
        v = pl.update(mock_solve(float(pl.lam[0])), growth=1.0, slow_ratio=0.3, eps_max=2.0, previous=v)
    assert pl.lam[0] == pytest.approx(star, rel=1e-12)
    assert pl.pbar[0] == pytest.approx(star, rel=1e-12)
