"""Frictional contact against independent codes: the peers 'dome' and 'mammo' cases.

Reference data: ../shared/data/peers (CalculiX 2.20, FEBio 2.9, SfePy; settings in its
README.md).  Runs the cases too long for the test suite on a shared 2-core machine
(dome mu = 0 / 0.1 on 4,844 nodes; mammo mu = 0.1 on 3,102 nodes) with plain P1 (like
with like: the references are tet4) and prints, per case: plate force (mN) against each
code, relRMS (RMS nodal displacement difference / max reference displacement), Newton
iterations, augmentations, cut-backs, wall and CPU seconds.  Gravity is ramped in 4
increments, the plate moved in increments of 2.5 mm of travel (the protocols' default cap).

    .venv/bin/python pipelines/peers_contact.py [--cases dome0 dome01 mammo01]
        [--contact penetration_tol_mm=0.005 ...]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from regtrack.config import config_from_assignments, parse_assignments
from regtrack.errors import ConfigError
from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.contact import ContactConfig, PlateContact, tributary_areas
from regtrack.mechanics.meshes import boundary_faces, orient_tets
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.plates import RigidPlate
from regtrack.mechanics.problem import build_problem
from regtrack.model.types import AnatomicalFrame, BreastModel

PEERS = Path(os.environ.get("REGTRACK_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) / "peers"


def load(mesh: str) -> BreastModel:
    import meshio

    m = meshio.read(PEERS / "meshes" / mesh)
    X = np.asarray(m.points, float)
    tets = orient_tets(X, m.cells_dict["tetra"])
    region = np.where(m.cell_data_dict["gmsh:physical"]["tetra"] == 2, 2, 1)
    return BreastModel(points=X, tets=tets, region=region, tumour_id=(region == 2).astype(int),
                       skin=boundary_faces(X, tets), fixed=np.zeros(len(X), bool), nipple=0,
                       frame=AnatomicalFrame(np.zeros(3), np.eye(3), "R"))


def off_planes(X, tris, axes):
    on = np.zeros(len(tris), bool)
    for k in axes:
        on |= np.all(np.abs(X[tris][:, :, k]) < 1e-9, axis=1)
    return tris[~on]


def rel_rms(u, ref):
    return float(np.sqrt(((u - ref) ** 2).sum(1).mean()) / np.abs(ref).max())


def plate(model, tris, name, origin, normal, cfg, eps):
    nodes = np.unique(tris)
    pl = RigidPlate(name=name, origin=origin, normal=normal, e1=(1, 0, 0))
    return PlateContact(pl, model.points, nodes, tributary_areas(model.points, tris)[nodes],
                        config=cfg, penalty=eps)


def run_case(case: str, contact_kw: dict) -> dict:
    mu = 0.0 if case.endswith("0") and not case.endswith("01") else 0.1
    kind = "dome" if case.startswith("dome") else "mammo"
    model = load("dome_tumor_lc4.msh" if kind == "dome" else "mammo_tumor_lc5.msh")
    X = model.points
    prob = build_problem(model, MechanicsConfig(tissue_c1_kpa=1.0, tumour_c1_kpa=10.0, nu=0.49,
                                                formulation="p1", skin_enabled=False))
    cfg = ContactConfig(friction=mu, penetration_tol_mm=0.01, **contact_kw)
    if kind == "dome":
        base = np.flatnonzero(np.abs(X[:, 2]) < 1e-9)
        dofs = (3 * base[:, None] + np.arange(3)).ravel()
        tris = off_planes(X, model.skin, (2,))
        up = plate(model, tris, "upper", (0, 0, 50), (0, 0, -1), cfg, 0.1)
        contribs, travel = [up], ((0, 0, 50), (0, 0, 35))
    else:
        dofs = np.concatenate([3 * np.flatnonzero(np.abs(X[:, 0]) < 1e-9),
                               3 * np.flatnonzero(np.abs(X[:, 1]) < 1e-9) + 1])
        tris = off_planes(X, model.skin, (0,))
        up = plate(model, tris, "upper", (0, 0, 50), (0, 0, -1), cfg, 0.1)
        lo = plate(model, tris, "lower", (0, 0, -49.5), (0, 0, 1), cfg, 0.1)
        contribs, travel = [up, lo], ((0, 0, 50), (0, 0, 20))
    bc = lambda t: (dofs, 0.0)  # noqa: E731
    t0, c0 = time.perf_counter(), time.process_time()
    u, s1, _ = minimise_step(prob, np.zeros_like(X), gravity=lambda t: np.array([0, 0, -9.81 * t]),
                             dirichlet=bc, contacts=contribs, n_increments=4, step_name="gravity")
    up.set_motion(*travel)
    n_plate = int(np.ceil(np.linalg.norm(np.subtract(travel[1], travel[0])) / 2.5))
    u, s2, _ = minimise_step(prob, u, gravity=lambda t: np.array([0, 0, -9.81]), dirichlet=bc,
                             contacts=contribs, n_increments=n_plate, step_name="plate")
    out = {"case": case, "mu": mu, "force_mN": up.report(u)["normal_force_N"] * 1e3,
           "iterations": [s1.iterations, s2.iterations],
           "augmentations": [s1.augmentations, s2.augmentations],
           "cutbacks": [s1.cutbacks, s2.cutbacks],
           "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "refs": {}}
    tag = {"dome0": ["dome_sf", "dome_fb_mu0", "dome_ccx_mu0"], "dome01": ["dome_fb_mu01", "dome_ccx_mu01"],
           "mammo01": ["mammo_fb_mu01", "mammo_ccx_mu01"], "mammo0": ["mammo_sf", "mammo_fb_mu0", "mammo_ccx_mu0"]}[case]
    for name in tag:
        ref = np.load(PEERS / "results" / f"{name}.npz")
        out["refs"][name] = {"force_mN": float(ref["hist_force_upper"][-1]), "relRMS": rel_rms(u, ref["u"])}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["dome0", "dome01", "mammo01"],
                    choices=["dome0", "dome01", "mammo0", "mammo01"])
    ap.add_argument("--contact", nargs="*", default=[], help="ContactConfig overrides key=value")
    args = ap.parse_args()
    try:
        config_from_assignments(ContactConfig, args.contact, where="--contact")  # validates them
    except ConfigError as exc:
        ap.error(str(exc))
    kw = parse_assignments(args.contact, where="--contact")
    for case in args.cases:
        r = run_case(case, kw)
        print(f"{case}: force {r['force_mN']:.1f} mN; iterations gravity/plate {r['iterations']}, "
              f"augmentations {r['augmentations']}, cut-backs {r['cutbacks']}; "
              f"{r['wall_s']:.0f} s wall, {r['cpu_s']:.0f} s CPU")
        for name, ref in r["refs"].items():
            print(f"    vs {name:14s}: force {ref['force_mN']:.1f} mN ({100 * (r['force_mN'] / ref['force_mN'] - 1):+.2f} %), "
                  f"relRMS {ref['relRMS']:.2e}")


if __name__ == "__main__":
    main()
