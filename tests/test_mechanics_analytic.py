"""Mechanics core vs closed forms: uniaxial cube, patch test, gravity column, peers' cube.

The peers' cube results come from CalculiX 2.20, FEBio 2.9 and SfePy
(../shared/data/peers, see its README.md).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.optimize import brentq

from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.mechanics.materials import bulk_modulus, young_modulus
from regtrack.mechanics.meshes import box_model
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.p2 import model_to_p2
from regtrack.mechanics.problem import build_problem, reaction_forces
from tests.conftest import shared_data

L = 10.0


def roller_dirichlet(X, top_disp):
    """Symmetry rollers on x=0, y=0, z=0 and prescribed u_z = top_disp * t on z = max."""
    dofs, vals = [], []
    for ax in range(3):
        n0 = np.flatnonzero(np.abs(X[:, ax]) < 1e-9)
        dofs.append(3 * n0 + ax)
        vals.append(np.zeros(len(n0)))
    top = np.flatnonzero(np.abs(X[:, 2] - X[:, 2].max()) < 1e-9)
    dofs = np.concatenate(dofs + [3 * top + 2])

    def dirichlet(t):
        return dofs, np.concatenate(vals + [np.full(len(top), top_disp * t)])

    return dirichlet, top


def closed_form_uniaxial(c1, nu, lam):
    """Nominal stress P11 (MPa) and lateral stretch of W = c1(I1bar-3) + K/2 (J-1)^2 under
    uniaxial stretch ``lam`` with traction-free lateral faces (lateral stretch by root-finding)."""
    K = bulk_modulus(2 * c1, nu)

    def dW(l1, l2):  # dW/dl1 with l2 = l3
        J = l1 * l2 * l2
        I1 = l1 * l1 + 2 * l2 * l2
        return c1 * J ** (-2 / 3) * (2 * l1 - 2 / 3 * I1 / l1) + K * (J - 1) * J / l1

    def lateral_traction(l2):  # dW/dl2 at (lam, l2, l2) must vanish
        J = lam * l2 * l2
        I1 = lam * lam + 2 * l2 * l2
        return c1 * J ** (-2 / 3) * (2 * l2 - 2 / 3 * I1 / l2) + K * (J - 1) * J / l2

    l2 = brentq(lateral_traction, 0.5, 2.0)
    return dW(lam, l2), l2


@pytest.mark.parametrize("formulation", ["p1-anp", "p1", "p2"])
@pytest.mark.parametrize("nu", [0.45, 0.499])
def test_cube_uniaxial_compression_matches_closed_form(formulation, nu):
    # 30 % compression; the state is homogeneous, so any consistent formulation must be
    # exact up to the solver's tolerance: 1 % (the acceptance bound) is very loose here.
    c1 = 1e-3
    cfg = MechanicsConfig(formulation=formulation, tissue_c1_kpa=1.0, nu=nu, skin_enabled=False)
    model = box_model((L, L, L), (3, 3, 3) if formulation != "p2" else (2, 2, 2))
    pr = build_problem(model_to_p2(model) if formulation == "p2" else model, cfg)
    dirichlet, top = roller_dirichlet(pr.X, -0.3 * L)
    u, st, _ = minimise_step(pr, np.zeros_like(pr.X), dirichlet=dirichlet, n_increments=4, step_name="cube")
    force = -reaction_forces(pr, u)[top, 2].sum()
    P, l2 = closed_form_uniaxial(c1, nu, 0.7)
    assert force == pytest.approx(-P * L * L, rel=1e-2)
    lateral = 1 + u[np.argmax(pr.X[:, 0] + pr.X[:, 1]), 0] / L
    assert lateral == pytest.approx(l2, rel=1e-3)
    assert st.cutbacks == 0


def test_closed_form_matches_peers_statement():
    # peers/README.md: c1 = 1 kPa, nu = 0.49, lambda = 0.7 -> 266.71 mN, lateral 1.19145
    P, l2 = closed_form_uniaxial(1e-3, 0.49, 0.7)
    assert -P * 100 * 1e3 == pytest.approx(266.71, abs=0.01)
    assert l2 == pytest.approx(1.19145, abs=1e-5)


def test_peers_cube_like_with_like():
    """Plain P1 on the peers' tet4 cube10.msh vs CalculiX / FEBio / SfePy nodal displacements."""
    import meshio

    from regtrack.mechanics.meshes import boundary_faces, orient_tets
    from regtrack.model.types import AnatomicalFrame, BreastModel

    msh = meshio.read(shared_data("peers", "meshes", "cube10.msh"))
    tets = orient_tets(msh.points, msh.cells_dict["tetra"])
    used = np.unique(tets)
    assert len(used) == len(msh.points)
    model = BreastModel(msh.points, tets, np.ones(len(tets)), np.zeros(len(tets)), boundary_faces(msh.points, tets),
                        np.zeros(len(msh.points), bool), 0, AnatomicalFrame(np.zeros(3), np.eye(3), "R"))
    cfg = MechanicsConfig(formulation="p1", tissue_c1_kpa=1.0, nu=0.49, skin_enabled=False)
    pr = build_problem(model, cfg)
    dirichlet, top = roller_dirichlet(pr.X, -3.0)
    u, _, _ = minimise_step(pr, np.zeros_like(pr.X), dirichlet=dirichlet, n_increments=4)
    force_mn = -reaction_forces(pr, u)[top, 2].sum() * 1e3
    assert force_mn == pytest.approx(266.71, rel=1e-3)  # the codes agree within 0.09 %
    for code in ("ccx", "fb", "sf"):
        ref = np.load(shared_data("peers", "results", f"cube_{code}.npz"))
        assert np.allclose(ref["X"], pr.X)
        rel_rms = np.sqrt(np.mean(np.sum((u - ref["u"]) ** 2, axis=1))) / np.abs(ref["u"]).max()
        # penalty contact in the peers leaves ~1e-3 differences (peers/README.md)
        assert rel_rms < 2e-3, (code, rel_rms, json.loads(str(ref["meta"]))["solver"])


@pytest.mark.parametrize("formulation", ["p1-anp", "p1"])
def test_patch_test_affine_deformation(formulation):
    """Irregular mesh, affine finite deformation on the boundary: interior nodes must
    follow the same affine map and the reaction must equal P(F) times the face area."""
    model = box_model((2.0, 1.0, 1.0), (4, 3, 3))
    rng = np.random.default_rng(1)
    X = model.points
    inner = np.all((X > 1e-9) & (X < np.array([2.0, 1.0, 1.0]) - 1e-9), axis=1)
    X[inner] += 0.08 * rng.uniform(-1, 1, (inner.sum(), 3))
    F = np.array([[1.1, 0.05, 0.0], [0.02, 0.95, 0.03], [0.0, -0.04, 1.02]])
    cfg = MechanicsConfig(formulation=formulation, nu=0.45, skin_enabled=False)
    pr = build_problem(model, cfg)
    bnd = np.flatnonzero(~inner)
    target = (X @ (F - np.eye(3)).T)
    dofs = (3 * bnd[:, None] + np.arange(3)).reshape(-1)
    # the patch test checks the formulation, so Newton is driven far below its default
    # tolerances (1e-4 leaves ~1e-6 mm here, depending on how exact the inexact solves were)
    strict = SolverOptions(force_tol=1e-11, balance_tol=1e-11, disp_abs_tol_mm=1e-11)
    u, _, _ = minimise_step(pr, np.zeros_like(X), dirichlet=lambda t: (dofs, t * target[bnd].reshape(-1)),
                            n_increments=4, options=strict)
    assert np.abs(u[inner] - target[inner]).max() < 1e-8
    R = reaction_forces(pr, u)
    assert np.abs(R[inner]).max() < 1e-10


@pytest.mark.parametrize("formulation, nu", [("p1-anp", 0.3), ("p1", 0.3), ("p1-anp", 0.49), ("p2", 0.49)])
def test_gravity_column_small_strain(formulation, nu):
    """Column of height H on rollers under its own weight: top settlement
    rho g H^2 / (2 E) in the small-strain limit (2 %: discretisation + nonlinearity at
    strain ~1e-4)."""
    H, a = 40.0, 4.0
    cfg = MechanicsConfig(formulation=formulation, nu=nu, skin_enabled=False)
    model = box_model((a, a, H), (2, 2, 10) if formulation != "p2" else (1, 1, 5))
    pr = build_problem(model_to_p2(model) if formulation == "p2" else model, cfg)
    X = pr.X
    dofs = np.concatenate([3 * np.flatnonzero(np.abs(X[:, ax]) < 1e-9) + ax for ax in range(3)])
    g = 0.01 * 9.81
    u, _, _ = minimise_step(pr, np.zeros_like(X), gravity=lambda t: np.array([0, 0, -g * t]),
                            dirichlet=lambda t: (dofs, np.zeros(len(dofs))), n_increments=1)
    E = young_modulus(cfg.tissue_c1_kpa * 1e-3, cfg.nu)
    expected = 1000 * g * 1e-9 * H**2 / (2 * E)
    top = np.abs(X[:, 2] - H) < 1e-9
    assert -u[top, 2].mean() == pytest.approx(expected, rel=0.02)
    # reaction balances the weight exactly
    R = reaction_forces(pr, u, gravity_ms2=np.array([0, 0, -g]))
    assert R[:, 2].sum() == pytest.approx(1000 * g * 1e-9 * a * a * H, rel=1e-8)
