"""Volumetric locking: Cook's membrane (plane strain, nu = 0.499), bending dominated.

Cook's tapered panel (corners (0,0), (48,44), (48,60), (0,44) mm) is clamped on the left
edge and loaded by a uniform vertical shear on the right edge, one tet layer thick with
u_z = 0 (plane strain).  The average-nodal-pressure tet must converge under refinement
and be within 5 % of the converged tip deflection on the 32 x 32 mesh, while plain P1
on the same mesh stays far too stiff (locking).  The converged value is confirmed by an
independent discretisation, 10-node tets (P2), which converge to the same limit (P2
16 x 16: 0.623 mm vs ANP 64 x 64: 0.630 mm; Richardson limits 0.638 / 0.643 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.loads import traction_forces
from regtrack.mechanics.meshes import box_model, boundary_faces
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.p2 import boundary_faces6, model_to_p2
from regtrack.mechanics.problem import build_problem

FORCE_N = 0.02  # small: near-linear response, tip deflection ~0.6 mm on a 48 mm panel


def cook_tip_deflection(n: int, formulation: str, nu: float = 0.499) -> float:
    m = box_model((1, 1, 1), (n, n, 1))
    xi, eta = m.points[:, 0].copy(), m.points[:, 1].copy()
    corners = [np.array(c, float) for c in ((0, 0), (48, 44), (48, 60), (0, 44))]
    w = [(1 - xi) * (1 - eta), xi * (1 - eta), xi * eta, (1 - xi) * eta]
    m.points[:, :2] = sum(wi[:, None] * c for wi, c in zip(w, corners))
    m.fixed = np.abs(m.points[:, 0]) < 1e-9
    if formulation == "p2":
        m = model_to_p2(m)
    cfg = MechanicsConfig(formulation=formulation, tissue_c1_kpa=100.0, nu=nu, skin_enabled=False)
    pr = build_problem(m, cfg)
    faces = boundary_faces6(pr.X, pr.tets) if formulation == "p2" else boundary_faces(pr.X, pr.tets)
    right = faces[np.all(np.abs(pr.X[faces][:, :, 0] - 48) < 1e-9, axis=1)]
    f = traction_forces(pr.X, right, np.array([0.0, FORCE_N / 16.0, 0.0]))  # 16 mm x 1 mm face
    zd = 3 * np.arange(pr.n_nodes) + 2
    u, _, _ = minimise_step(pr, np.zeros_like(pr.X), dirichlet=lambda t: (zd, np.zeros(len(zd))),
                            forces=lambda t: t * f, n_increments=1)
    tip = (np.abs(pr.X[:, 0] - 48) < 1e-9) & (np.abs(pr.X[:, 1] - 60) < 1e-9)
    return float(u[tip, 1].mean())


@pytest.mark.slow
def test_cook_membrane_anp_is_locking_free_p1_locks():
    anp = {n: cook_tip_deflection(n, "p1-anp") for n in (8, 16, 32, 64)}
    p1_32 = cook_tip_deflection(32, "p1")
    # convergence under refinement: monotone, with shrinking differences
    d = np.diff([anp[n] for n in (8, 16, 32, 64)])
    assert np.all(d > 0) and d[1] < 0.6 * d[0] and d[2] < 0.6 * d[1]
    # Richardson estimate of the limit from the 16/32/64 sequence (observed order)
    r = d[1] / d[2]
    limit = anp[64] + d[2] / (r - 1)
    assert anp[64] == pytest.approx(limit, rel=0.03)
    converged = anp[64]
    # the acceptance statement: ANP within 5 % of the converged value on the coarse 32 x 32 mesh
    assert abs(anp[32] - converged) / converged < 0.05
    # ... while plain P1 on the same mesh is far too stiff (volumetric locking)
    assert p1_32 < 0.6 * converged
    # independent confirmation of the converged value: quadratic tets (P2) on 16 x 16
    assert cook_tip_deflection(16, "p2") == pytest.approx(converged, rel=0.03)


def test_anp_group_pressure_kernel_sums_like_numpy():
    """problem._anp_pressure gives the group volume ratios and element pressures of the
    numpy expressions it replaced (bincount over the flat corners, mean over each
    element's four groups) to the bit, on a distorted box."""
    from regtrack.mechanics import tissue
    from regtrack.mechanics.problem import _anp_pressure

    m = box_model((3.0, 2.0, 2.0), (5, 4, 3))
    pr = build_problem(m, MechanicsConfig(nu=0.49))
    grp = pr.groups
    x = pr.X + 0.05 * np.random.default_rng(4).standard_normal(pr.X.shape)
    Je = tissue.jacobians(x, pr.tets, pr.G)
    vg = np.bincount(grp.of.reshape(-1), weights=np.repeat(pr.V * Je / 4.0, 4), minlength=grp.n_groups)
    Jg = vg / grp.vol0
    p = (grp.kappa * (Jg - 1.0))[grp.of].mean(axis=1)
    Jg2, p2 = _anp_pressure(grp.of, pr.V, Je, grp.vol0, grp.kappa)
    assert np.array_equal(Jg, Jg2) and np.array_equal(p, p2)
    assert np.abs(Jg - 1.0).max() > 1e-3  # distorted: the test sees real volume changes
