"""Contact mechanics against independent finite-element codes and closed forms (issue 5).

Reference data: ../shared/data/peers (CalculiX 2.20, FEBio 2.9 and SfePy results on the
same meshes; settings in peers/README.md).  Units there: mm, kPa, mN; ours: mm, MPa, N.
relRMS = RMS nodal displacement difference / max reference displacement.

Tolerances and why:
* cube (homogeneous, closed form 266.71 mN): P1 is exact for homogeneous strain; the
  augmented-Lagrangian leaves < 1e-4 mm of penetration on 3 mm of travel -> 0.3 %.
* Hertz, plain P1 vs the tet4 references (like with like): the codes agree with each other
  to 0.5 % in force and 1.4e-3 relRMS; we ask 1 % and 2e-3.
* Hertz, locking-free (average nodal pressure) vs the closed form F = 4/3 E* R^1/2 d^3/2,
  a = (R d)^1/2 at small indentation (d <= 0.3 mm = 0.6 % of R): 5 % (issue 5); the tet10
  references themselves are 0.5-4.6 % above Hertz on this mesh.
* mammo with friction 0.1 vs CalculiX (peers/README.md: trust CalculiX's forces with
  friction; FEBio's frictional run stopped with a 34 mN residual): the codes' penalties
  differ, and CalculiX's own result moves by < 3e-4 mm across its stick slopes; we ask
  0.3 % in force and relRMS < 1.5e-3 (measured 0.05 % and 3.1e-4), and that friction
  raises the plate force over the frictionless run, as it does in CalculiX (+10.4 mN).
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.contact import ContactConfig, PlateContact, tributary_areas
from regtrack.mechanics.meshes import boundary_faces, orient_tets
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.plates import RigidPlate
from regtrack.mechanics.problem import build_problem
from regtrack.model.types import AnatomicalFrame, BreastModel
from tests.conftest import shared_data

pytestmark = pytest.mark.realdata

C1_MPA, NU = 1e-3, 0.49
E_STAR = 4 * C1_MPA * (1 + NU) / (1 - NU**2)  # plane-strain modulus of the small-strain limit


def _load(mesh: str):
    import meshio

    m = meshio.read(shared_data("peers", "meshes", mesh))
    X = np.asarray(m.points, float)
    tets = orient_tets(X, m.cells_dict["tetra"])
    tag = m.cell_data_dict["gmsh:physical"]["tetra"]
    region = np.where(tag == 2, 2, 1)
    model = BreastModel(points=X, tets=tets, region=region, tumour_id=(region == 2).astype(int),
                        skin=boundary_faces(X, tets), fixed=np.zeros(len(X), bool), nipple=0,
                        frame=AnatomicalFrame(np.zeros(3), np.eye(3), "R"))
    return model


def _ref(name: str):
    return np.load(shared_data("peers", "results", f"{name}.npz"))


def _problem(model, formulation: str):
    cfg = MechanicsConfig(tissue_c1_kpa=1.0, tumour_c1_kpa=10.0, nu=NU, formulation=formulation,
                          skin_enabled=False)
    return build_problem(model, cfg)


def _plate_contact(model, tris, plate, *, mu=0.0, tol=1e-3, eps=0.05):
    nodes = np.unique(tris)
    return PlateContact(plate, model.points, nodes, tributary_areas(model.points, tris)[nodes],
                        config=ContactConfig(friction=mu, penetration_tol_mm=tol), penalty=eps)


def _off_planes(X, tris, axes):
    """Skin triangles not lying on the symmetry planes x_k = 0 (k in axes)."""
    on = np.zeros(len(tris), bool)
    for k in axes:
        on |= np.all(np.abs(X[tris][:, :, k]) < 1e-9, axis=1)
    return tris[~on]


def _rollers(X, axes):
    return np.concatenate([3 * np.flatnonzero(np.abs(X[:, k]) < 1e-9) + k for k in axes])


def rel_rms(u, ref):
    return float(np.sqrt(((u - ref) ** 2).sum(1).mean()) / np.abs(ref).max())


def cube_case():
    """The peers' cube: (points, problem, upper plate contact moving 10 -> 7 mm, roller dofs
    on the three symmetry planes)."""
    model = _load("cube10.msh")
    X = model.points
    prob = _problem(model, "p1")
    plate = RigidPlate(name="upper", origin=(0, 0, 10), normal=(0, 0, -1), e1=(1, 0, 0))
    c = _plate_contact(model, _off_planes(X, model.skin, (0, 1, 2)), plate, tol=1e-4, eps=1.0)
    c.set_motion((0, 0, 10), (0, 0, 7))
    return X, prob, c, _rollers(X, (0, 1, 2))


def test_cube_against_closed_form_and_codes():
    X, prob, c, roll = cube_case()
    u, _, _ = minimise_step(prob, np.zeros_like(X), dirichlet=lambda t: (roll, 0.0), contacts=[c],
                            n_increments=4)
    force_mn = c.report(u)["normal_force_N"] * 1e3
    assert force_mn == pytest.approx(266.71, rel=3e-3)
    corner = np.argmax(X.sum(1))
    assert 1 + u[corner, 0] / 10.0 == pytest.approx(1.19145, rel=1e-3)
    for code in ("ccx", "fb", "sf"):
        assert rel_rms(u, _ref(f"cube_{code}")["u"]) < 2e-3, code


def _hertz(formulation: str, tol: float):
    model = _load("hertz_q_fine.msh")
    X = model.points
    prob = _problem(model, formulation)
    plate = RigidPlate(name="upper", origin=(0, 0, 50), normal=(0, 0, -1), e1=(1, 0, 0))
    c = _plate_contact(model, _off_planes(X, model.skin, (0, 1, 2)), plate, tol=tol)
    roll = _rollers(X, (0, 1, 2))
    # the force history is read every 0.1 mm, so each 0.1 mm is a step of its own, whose
    # (last) increment iterates the multipliers to the tolerance
    u, hist = np.zeros_like(X), []
    for k in range(10):
        c.set_motion((0, 0, 50 - 0.1 * k), (0, 0, 50 - 0.1 * (k + 1)))
        u, _, _ = minimise_step(prob, u, dirichlet=lambda t: (roll, 0.0), contacts=[c], n_increments=1)
        c.motion = None
        hist.append((0.1 * (k + 1), 4 * c.report(u)["normal_force_N"]))  # full sphere
    return model, u, c, hist


def hertz_force(d_mm: float, R: float = 50.0) -> float:
    """Hertz: F = 4/3 E* sqrt(R) d^(3/2) (N), E* = E / (1 - nu^2)."""
    return 4.0 / 3.0 * E_STAR * np.sqrt(R) * d_mm**1.5


@pytest.mark.slow
def test_hertz_plain_p1_matches_tet4_references():
    model, u, c, hist = _hertz("p1", tol=1e-3)
    f_quarter_mn = hist[-1][1] / 4 * 1e3
    for code in ("ccx", "fb", "sf"):
        ref = _ref(f"hertz_{code}_p1")
        assert f_quarter_mn == pytest.approx(ref["hist_force_upper"][-1], rel=0.01), code
        assert rel_rms(u, ref["u"]) < 2e-3, code
    # and plain P1 is the known 15-20 % too stiff against Hertz (locking, peers/README.md)
    assert 1.12 < hist[-1][1] / hertz_force(1.0) < 1.25


@pytest.mark.slow
def test_hertz_locking_free_matches_closed_form():
    model, u, c, hist = _hertz("p1-anp", tol=1e-3)
    for t, f in hist:
        if t <= 0.3 + 1e-9:
            assert f == pytest.approx(hertz_force(t), rel=0.05), f"indentation {t} mm"
    # close to the tet10 references at the full 1 mm
    for code in ("ccx", "sf"):
        ref = _ref(f"hertz_{code}_p2")["hist_force_upper"][-1] * 4e-3
        assert hist[-1][1] == pytest.approx(ref, rel=0.03), code
    # contact radius: fit Hertz's p(r)^2 = p0^2 (1 - r^2 / a^2) to the nodal pressures
    _, st = c.nodal_forces(u)
    act = st["active"]
    x = (model.points + u)[c.nodes][act]
    r2 = x[:, 0] ** 2 + x[:, 1] ** 2
    coef = np.linalg.lstsq(np.column_stack([np.ones(len(r2)), r2]), st["pressure"][act] ** 2,
                           rcond=None)[0]
    a_fit = np.sqrt(-coef[0] / coef[1])
    assert a_fit == pytest.approx(np.sqrt(50.0 * 1.0), rel=0.05)


def mammo_case(mu: float):
    """peers 'mammo': (points, problem, upper and lower plate contacts, the roller
    constraint ``t -> (dofs, 0)``): u_x = 0 on the chest wall x = 0, u_y = 0 on y = 0, the
    lower plate fixed at z = -49.5 (0.5 mm overlap), the upper plate at z = 50."""
    model = _load("mammo_tumor_lc5.msh")
    X = model.points
    prob = _problem(model, "p1")
    dofs = np.concatenate([3 * np.flatnonzero(np.abs(X[:, 0]) < 1e-9),
                           3 * np.flatnonzero(np.abs(X[:, 1]) < 1e-9) + 1])
    tris = _off_planes(X, model.skin, (0,))
    up = _plate_contact(model, tris, RigidPlate(name="upper", origin=(0, 0, 50), normal=(0, 0, -1),
                                                e1=(1, 0, 0)), mu=mu, tol=0.01, eps=0.1)
    lo = _plate_contact(model, tris, RigidPlate(name="lower", origin=(0, 0, -49.5), normal=(0, 0, 1),
                                                e1=(1, 0, 0)), mu=mu, tol=0.01, eps=0.1)
    return X, prob, up, lo, (lambda t: (dofs, 0.0))


def _mammo(mu: float):
    """peers 'mammo' (:func:`mammo_case`): gravity -z (ramped, 4 increments), then the upper
    plate 50 -> 20 in 12 increments (2.5 mm of travel each, the protocols' default cap)."""
    X, prob, up, lo, bc = mammo_case(mu)
    u, _, _ = minimise_step(prob, np.zeros_like(X), gravity=lambda t: np.array([0, 0, -9.81 * t]),
                            dirichlet=bc, contacts=[up, lo], n_increments=4)
    up.set_motion((0, 0, 50), (0, 0, 20))
    u, _, _ = minimise_step(prob, u, gravity=lambda t: np.array([0, 0, -9.81]), dirichlet=bc,
                            contacts=[up, lo], n_increments=12)
    tumour = int(np.argmin(np.linalg.norm(X - [25.0, 0.0, 0.0], axis=1)))
    return u, up.report(u)["normal_force_N"] * 1e3, tumour


@pytest.mark.slow
def test_mammo_frictionless_matches_three_codes():
    """Measured: 2362.3 mN (ccx 2361.5, sf 2362.3, fb 2357.7); relRMS 4.8e-5 / 5.6e-5 /
    2.4e-4; tumour-centre displacement within 1e-3 mm of CalculiX."""
    u, force, tum = _mammo(0.0)
    for name in ("mammo_ccx_mu0", "mammo_sf", "mammo_fb_mu0"):
        ref = _ref(name)
        assert force == pytest.approx(ref["hist_force_upper"][-1], rel=3e-3), name
        assert rel_rms(u, ref["u"]) < 1e-3, name
    np.testing.assert_allclose(u[tum], _ref("mammo_ccx_mu0")["u"][tum], atol=0.02)


@pytest.mark.slow
def test_mammo_friction_matches_calculix():
    """Measured (friction 0.1): 2373.2 mN vs CalculiX 2371.9 mN, relRMS 3.1e-4."""
    u, force, tum = _mammo(0.1)
    ref = _ref("mammo_ccx_mu01")
    assert force == pytest.approx(ref["hist_force_upper"][-1], rel=3e-3)
    assert rel_rms(u, ref["u"]) < 1.5e-3
    # friction raises the plate force (the lower plate holds the base back): the same
    # direction and size as CalculiX's mu 0 -> 0.1 change (2361.5 -> 2371.9 mN)
    f0 = _ref("mammo_ccx_mu0")["hist_force_upper"][-1]
    assert 0.5 < (force - f0) / (ref["hist_force_upper"][-1] - f0) < 2.0
    # and the displacements differ from the frictionless reference by more than the
    # agreement with the frictional one (a frictionless solver would fail here)
    assert rel_rms(u, _ref("mammo_ccx_mu0")["u"]) > 3 * rel_rms(u, ref["u"])
