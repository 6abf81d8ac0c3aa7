"""``regtrack.model`` on the phantom sample case and on a real exam.

Real data: Pelicano et al., Sensors 2021 / PLoS One 2024 (label maps of prone breast MRI,
Hospital da Luz, Lisbon), read through ``shared_data``.  The acceptance targets of issue 3
are asserted: no inverted tets, min dihedral > 5 deg, 5th-percentile gamma > 0.3, breast
volume within 3 % and every kept tumour within 10 % of its voxel volume, mean surface
distance under one voxel.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SAMPLE_CASES, shared_data
from regtrack.cli import main as cli_main
from regtrack.imaging.readers import read_label_map
from regtrack.model.build import build_model
from regtrack.model.config import MeshConfig
from regtrack.model.io import load_model
from regtrack.model.labels import PRESETS


def assert_targets(q: dict, *, voxel_mm: float = 1.0) -> None:
    assert q["n_inverted"] == 0
    assert q["min_dihedral_deg"] > 5.0
    assert q["gamma_p5"] > 0.3
    assert abs(q["volume_error"]) < 0.03
    for t in q["tumours"]:  # every kept tumour (issue 51; issue 3 checked those >= 1 ml)
        assert abs(t["volume_error"]) < 0.10
    assert q["surface_distance_mean_mm"] < voxel_mm


@pytest.mark.slow
def test_mesh_cli_on_phantom_case(tmp_path):
    case = SAMPLE_CASES / "phantom01"
    if not (case / "case.toml").is_file():
        pytest.skip("sample case phantom01 not present")
    out = tmp_path / "model.vtu"
    assert cli_main(["mesh", str(case), "--out", str(out), "--target-nodes", "5000"]) == 0
    m = load_model(out)
    side = json.loads(out.with_suffix(".json").read_text())
    assert_targets(side["meta"]["quality"])
    assert (tmp_path / "model_sections.png").is_file() and (tmp_path / "model_3d.png").is_file()
    assert m.frame.side == "R" and m.fixed.any() and len(m.skin) > 0
    # the phantom generator's nipple (case.toml comment): detection within 3 mm
    nip = m.frame.to_patient(m.points[m.nipple])
    assert np.linalg.norm(nip - [-95.0, -50.0, -8.0]) < 3.0
    assert np.allclose(m.points[m.nipple], 0.0, atol=1e-9)


@pytest.mark.slow
def test_phantom_coarse_mesh_meets_targets():
    """Coarse models (studies, fast tests) with the same defaults: 2,000 nodes.

    Regression: before surface remeshing a 3,000-node phantom lost its tissue volume
    (-98.8 %) or came out with 48,633 nodes.
    """
    case = SAMPLE_CASES / "phantom01"
    if not (case / "case.toml").is_file():
        pytest.skip("sample case phantom01 not present")
    labels = read_label_map(case / "mri" / "labels.nii.gz")
    m = build_model(labels, scheme=PRESETS["pelicano-detailed"], config=MeshConfig(target_nodes=2000), side="R")
    q = m.meta["quality"]
    assert_targets(q)
    # node count within the re-sizing tolerance (MeshConfig.node_tolerance = 35 %)
    assert 0.65 < m.n_nodes / 2000 < 1.35
    assert m.fixed.sum() > 20


@pytest.mark.slow
def test_sample_exam03_meets_targets():
    """Pelicano exam 03 (bundled sample case): failed before remeshing (min dihedral 1.5 deg)."""
    case = SAMPLE_CASES / "pelicano_exam03"
    if not (case / "case.toml").is_file():
        pytest.skip("sample case pelicano_exam03 not present")
    labels = read_label_map(case / "mri" / "labels.nii.gz")
    m = build_model(labels, scheme=PRESETS["pelicano-simple"], config=MeshConfig(), side="R")
    q = m.meta["quality"]
    assert_targets(q)
    assert 0.65 < m.n_nodes / 10000 < 1.35
    # the chest-wall cut face stays planar: every fixed node lies on the plane (half a voxel,
    # build.CUT_TOL_VOX) and they cover a broad base
    assert m.fixed.sum() > 100
    # every surface check passed before gmsh ran
    s = m.meta["attempts"][-1]["surfaces"]
    assert not s["problems"] and all(c["n_intersecting"] == 0 and c["n_open_edges"] == 0 for c in s["checks"])


@pytest.mark.slow
@pytest.mark.realdata
def test_real_exam_11_meets_targets():
    """Exam 11 failed every attempt before remeshing (gmsh: 'A segment and a facet intersect')."""
    f = shared_data("pelicano", "Exam_11", "Label_map_simple.zip")
    labels = read_label_map(f)
    m = build_model(labels, scheme=PRESETS["pelicano-simple"], config=MeshConfig())
    q = m.meta["quality"]
    assert_targets(q)
    # exam 11: one 6.2 ml tumour in the left breast
    assert m.frame.side == "L" and len(q["tumours"]) == 1
    assert q["tumours"][0]["voxel_volume_mm3"] == pytest.approx(6197.4, rel=1e-3)
    assert 0.65 < m.n_nodes / 10000 < 1.35
