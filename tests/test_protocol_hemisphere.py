"""Full CC and MLO protocols on a hemispherical breast with a tumour (real mechanics core).

A gmsh hemisphere (R = 50 mm, chest wall x = 0 fixed, 8 mm tumour) goes through the
shipped four-step protocols with their defaults.  Checked: the run completes, D hits
the target exactly (the plate gap is set from the measured uncompressed thickness), the
penetration stays under the 0.1 mm acceptance bound (augmented Lagrangian, 0.02 mm
tolerance), the global force balance closes (chest-wall reaction + plate forces +
weight = 0, to the solver's 1e-6 relative residual; 1e-4 of the plate force is asked),
and the result files are written.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.meshes import hemisphere_model
from regtrack.mechanics.protocol import shipped_protocol
from regtrack.mechanics.run_view import run_protocol_on_model, write_outputs
from regtrack.mechanics.support import squeeze_weights


@pytest.fixture(scope="module")
def model():
    return hemisphere_model(50.0, 10.0, tumour_radius=8.0)


def _balance(model, rec):
    weight = 1000.0 * model.tet_volumes().sum() * 1e-9  # N per (m/s^2)
    on_body = -sum(np.asarray(c["force_N"]) for c in rec.contact.values())  # plates + chest wall
    return np.asarray(rec.solver["chest_wall_reaction_N"]) + on_body + weight * rec.gravity_ms2


@pytest.mark.slow
@pytest.mark.parametrize("view, target", [("cc", 0.38), ("mlo", 0.28)])
def test_shipped_protocol_runs_on_hemisphere(model, view, target, tmp_path):
    res, _ = run_protocol_on_model(model, shipped_protocol(view), mechanics=MechanicsConfig())
    assert res.complete
    last = res.steps[-1]
    assert last.D == pytest.approx(target, abs=1e-9)
    assert all(s.max_penetration_mm < 0.1 for s in res.steps)
    up = last.contact["upper"]["normal_force_N"]
    assert up > 0.5 and last.contact["lower"]["normal_force_N"] > 0
    for rec in res.steps:
        if "chest_wall_reaction_N" in rec.solver:
            assert np.abs(_balance(model, rec)).max() < MechanicsConfig().solver.balance_tol * max(up, 1.0), rec.name
    # once both plates hold the breast the body beyond the chest wall is squeezed with them
    # (regtrack.mechanics.support): the base follows, each node along the normal by its
    # share w of the travel (on average within 5 % of the travel: the layer's stretch),
    # and moves across it far less (the tissue's sideways bulge dragging the layer: under
    # 10 % of the travel; 6 % measured on the CC)
    touch = res.steps[-2].u  # the upper plate touches after the standing gravity, unsolved
    low = last.plates["lower"]
    n = np.asarray(low["normal"])
    t = np.cross([1.0, 0.0, 0.0], n)
    t /= np.linalg.norm(t)
    base = model.fixed
    w = squeeze_weights(model.points[base] + touch[base], low["origin_mm"], n, last.T0_mm)
    moved = (last.u[base] - touch[base]) @ n
    travel = last.T0_mm - last.gap_mm
    between = (w > 0) & (w < 1)
    assert between.sum() > 10
    assert abs(np.mean(-moved[between] - w[between] * travel)) < 0.05 * travel
    assert np.abs((last.u[base] - touch[base]) @ t).max() < 0.1 * travel
    files = write_outputs(res, model, tmp_path, stem=f"hemi_{view}")
    doc = json.loads(files["json"].read_text())
    assert doc["summary"]["D"] == pytest.approx(target)
    assert len(doc["steps"]) == 4 and files["png"].stat().st_size > 1000
    import meshio

    m = meshio.read(files["vtu"])
    np.testing.assert_allclose(m.point_data["displacement"], last.u)
    assert sum(k.startswith("displacement_") for k in m.point_data) == 4


@pytest.mark.slow
def test_plate_travel_per_increment_is_capped(model):
    """[contact] max_plate_increment_mm bounds the plate travel of every increment of a
    plate move (after its first 2 mm): the CC compression (36.9 mm of travel) takes at
    least ceil((36.9 - 2) / cap) + 1 increments, and the smooth hemisphere's plate force
    does not depend on it (measured: 14.098 N uncapped, 14.107 N at 5 mm, 14.114 N at
    1.25 mm; 0.2 % asked)."""
    from regtrack.mechanics.contact import ContactConfig

    out = {}
    for cap in (0.0, 2.5):
        res, _ = run_protocol_on_model(model, shipped_protocol("cc"), mechanics=MechanicsConfig(),
                                       contact=ContactConfig(max_plate_increment_mm=cap))
        last = res.steps[-1]
        out[cap] = (last.solver["increments"], last.contact["upper"]["normal_force_N"])
        travel = last.T0_mm - last.gap_mm
    assert out[2.5][0] >= np.ceil((travel - 2.0) / 2.5) + 1 > out[0.0][0]
    assert out[2.5][1] == pytest.approx(out[0.0][1], rel=2e-3)


def test_plates_press_the_faces_where_the_mri_cut_the_breast():
    """A breast cut by the MRI's field of view ends in flat faces without skin; on a CC the
    cranial and caudal cuts at the base are the first tissue the plates meet.  A 40 mm box
    on a fixed chest wall (x = 0) whose top and bottom faces (y = +-20 mm, parallel to the
    CC plates) are such cuts goes through the shipped CC protocol (skin membrane off, so
    that the skin triangles only say where the surface is): no node of any outer face ends
    inside a plate by more than the 0.1 mm acceptance bound, and the plate force is that
    of the same box with every outer face skin, to the solver's tolerance (0.5 % asked).
    Contact on the skin alone let the plates pass 14 mm into the cuts of a real CC."""
    from dataclasses import replace

    from regtrack.mechanics.meshes import boundary_faces, box_model
    from regtrack.model.checks import cut_faces

    base = box_model((40.0, 40.0, 40.0), (4, 4, 4), origin=(0.0, -20.0, -20.0))
    P = base.points
    fixed = np.isclose(P[:, 0], 0.0)
    faces = boundary_faces(P, base.tets)
    outer = faces[~fixed[faces].all(axis=1)]
    on_cut = np.isclose(np.abs(P[outer][:, :, 1]), 20.0).all(axis=1)
    nipple = int(np.argmax(P[:, 0] - np.abs(P[:, 1]) - np.abs(P[:, 2])))
    mech = MechanicsConfig(skin_enabled=False)
    force = {}
    for name, skin in (("cut", outer[~on_cut]), ("skin", outer)):
        model = replace(base, skin=skin, fixed=fixed, nipple=nipple)
        res, _ = run_protocol_on_model(model, shipped_protocol("cc"), mechanics=mech)
        last = res.steps[-1]
        assert res.complete and last.D == pytest.approx(0.38, abs=1e-9)
        x = P + last.u
        nodes = np.unique(outer)
        for pl in last.plates.values():
            gap = (x[nodes] - np.asarray(pl["origin_mm"])) @ np.asarray(pl["normal"])
            assert gap.min() > -0.1, (name, pl["name"])
        force[name] = last.contact["upper"]["normal_force_N"]
    assert len(cut_faces(base.tets, outer[~on_cut], fixed)) == 2 * 32
    assert force["cut"] == pytest.approx(force["skin"], rel=5e-3)
