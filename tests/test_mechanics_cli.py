"""`regtrack simulate --model M.vtu --config C.toml --out R.vtu` (file-level contract)."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest

from regtrack.cli import main
from regtrack.mechanics.meshes import box_model
from regtrack.model.io import save_model

CONFIG = """
[mechanics]
formulation = "p1-anp"
nu = 0.45
skin_enabled = true

[[steps]]
name = "standing gravity"
kind = "gravity"
vector_ms2 = [0.0, -9.81, 0.0]

[[steps]]
name = "push"
kind = "displacement"
node_set = "tip"
vector_mm = [-1.0, 0.0, 0.0]
"""


@pytest.fixture
def model_file(tmp_path):
    m = box_model((20.0, 10.0, 10.0), (4, 2, 2))
    m.fixed = m.points[:, 0] < 1e-9  # chest wall at x = 0
    path = tmp_path / "model.vtu"
    save_model(m, path)
    mesh = meshio.read(path)  # add a node-set field, as a user would in ParaView
    mesh.point_data["tip"] = (m.points[:, 0] > 20.0 - 1e-9).astype(np.int8)
    meshio.write(path, mesh)
    return path, m


def test_simulate_file_level(tmp_path, model_file):
    path, m = model_file
    cfg = tmp_path / "sim.toml"
    cfg.write_text(CONFIG)
    out = tmp_path / "res" / "result.vtu"
    assert main(["-q", "simulate", "--model", str(path), "--config", str(cfg), "--out", str(out)]) == 0
    res = meshio.read(out)
    assert {"displacement", "displacement_1_standing_gravity", "displacement_2_push", "reaction"} <= set(res.point_data)
    summary = json.loads(out.with_suffix(".json").read_text())
    g = summary["steps"][0]
    # after the gravity step the chest wall carries the whole weight: rho g V (N)
    weight = 1000 * 9.81e-9 * 20 * 10 * 10
    assert g["chest_wall_reaction_n"][1] == pytest.approx(weight, rel=1e-6)
    tip = m.points[:, 0] > 20 - 1e-9
    assert np.allclose(res.point_data["displacement"][tip, 0], res.point_data["displacement_1_standing_gravity"][tip, 0] - 1.0)
    assert summary["config"]["mechanics"]["nu"] == 0.45
    assert summary["solver"]["iterations"] > 0


@pytest.mark.parametrize("bad, match", [
    ("[[steps]]\nkind = 'gravity'\nvector_ms2 = [0, 1]\n", "vector_ms2"),
    ("[[steps]]\nkind = 'explode'\n", "kind"),
    ("[[steps]]\nkind = 'displacement'\nnode_set = 'nope'\nvector_mm = [1, 0, 0]\n", "node_set = 'nope'"),
    ("[mechanics]\nnu = 0.5\n[[steps]]\nkind = 'gravity'\n", "nu = 0.5"),
    ("[mechanics]\ntissue_c1_kpa = -1.0\n[[steps]]\nkind = 'gravity'\n", "tissue_c1_kpa"),
    ("", "no steps"),
])
def test_simulate_bad_config_names_the_key(tmp_path, model_file, capsys, bad, match):
    path, _ = model_file
    cfg = tmp_path / "bad.toml"
    cfg.write_text(bad)
    out = tmp_path / "r.vtu"
    assert main(["simulate", "--model", str(path), "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert match in err and str(cfg) in err
    assert not out.exists()


def test_simulate_function_api_gravity_then_unload():
    """Plain API: gravity on, then ramped back to zero: the body returns to its
    reference state (hyperelastic, path independent) within the solver tolerance, and the
    unloaded wall carries nothing: within 1e-9 N, ten times the residual an unloaded step
    is solved to (force_tol x FORCE_FLOOR_N = 1e-10 N; the box weighs 0.02 N)."""
    from regtrack.mechanics.config import MechanicsConfig
    from regtrack.mechanics.steps import LoadStep, simulate

    m = box_model((20.0, 10.0, 10.0), (4, 2, 2))
    m.fixed = m.points[:, 0] < 1e-9
    steps = [LoadStep("on", "gravity", (0.0, -9.81, 0.0), 0.0, 1.0),
             LoadStep("off", "gravity", (0.0, -9.81, 0.0), None, 0.0)]
    d = simulate(m, MechanicsConfig(), steps)
    sag = np.abs(d.steps[0].u).max()
    assert sag > 0.1  # soft tissue sags visibly (mm)
    assert np.abs(d.u).max() < 1e-6 * sag
    assert d.steps[1].chest_wall_reaction_n == pytest.approx(np.zeros(3), abs=1e-9)
    assert d.config["mechanics"]["tissue_c1_kpa"] == 0.54
