"""``regtrack project`` end to end on a small box model written in the file contracts."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest
from test_virtual_mammogram import _box

from regtrack.cli import main
from regtrack.model.io import save_model
from regtrack.model.types import AnatomicalFrame, BreastModel
from regtrack.virtual.surface import boundary_faces


@pytest.fixture
def box_case(tmp_path):
    # 40 (x, AP) x 30 (y, SI) x 50 (z, LR) mm box, chest wall at x = -40, nipple at the front
    pts, tets, reg = _box(8, 6, 10, (40.0, 30.0, 50.0), inner=((15, 10, 20), (25, 20, 30)))
    pts = pts - [40.0, 15.0, 25.0]
    fixed = np.isclose(pts[:, 0], -40.0)
    faces = boundary_faces(tets, pts)
    skin = faces[~fixed[faces].all(1)]
    nipple = int(np.argmin(np.linalg.norm(pts - [0.0, 0.0, 0.0], axis=1)))
    model = BreastModel(pts, tets, reg, (reg == 2).astype(int), skin, fixed, nipple,
                        AnatomicalFrame.standard("R"))
    save_model(model, tmp_path / "model.vtu")
    # "compression": y scaled by 0.5 about y = 0, x stretched by 1.5 (anterior of the wall)
    u = np.zeros_like(pts)
    u[:, 1] = -0.5 * pts[:, 1]
    u[:, 0] = 0.5 * (pts[:, 0] + 40.0)
    meshio.write(tmp_path / "result.vtu", meshio.Mesh(pts, [("tetra", tets)],
                                                      point_data={"displacement": u,
                                                                  "displacement_gravity": 0 * u}))
    return tmp_path


def test_project_cc_writes_json_and_pngs(box_case):
    out = box_case / "out"
    rc = main(["project", "--model", str(box_case / "model.vtu"), "--result",
               str(box_case / "result.vtu"), "--view", "cc", "--pixel", "0.5", "--out", str(out)])
    assert rc == 0
    doc = json.loads((out / "virtual_cc.json").read_text())
    bc = np.array(doc["breast_contour_mm"])
    # projected box: x in [-40, 20] (stretched), Y = -z in [-25, 25]; open contour = 3 sides
    assert bc[:, 0].max() == pytest.approx(20.0, abs=0.25)
    assert bc[:, 0].min() > -40.0 + 0.5
    assert np.abs(bc[:, 1]).max() == pytest.approx(25.0, abs=0.25)
    (tum,) = doc["tumour_contours_mm"]
    tum = np.array(tum)
    # tumour block x in [-25, -15] -> [-17.5, -2.5], z in [-5, 5]
    assert tum[:, 0].min() == pytest.approx(-17.5, abs=0.25)
    assert tum[:, 0].max() == pytest.approx(-2.5, abs=0.25)
    assert doc["meta"]["max_path_mm"] == pytest.approx(15.0, abs=1e-6)
    for name in ("virtual_cc_xray.png", "virtual_cc_overlay.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_project_step_and_errors(box_case, capsys):
    base = ["project", "--model", str(box_case / "model.vtu"), "--result",
            str(box_case / "result.vtu"), "--view", "MLO", "--out", str(box_case / "o")]
    assert main(base + ["--step", "gravity", "--pixel", "1"]) == 0
    assert (box_case / "o" / "virtual_mlo_gravity.json").is_file()
    assert main(base + ["--step", "nope"]) == 2
    err = capsys.readouterr().err
    assert "point data 'displacement_nope' missing (present: displacement, displacement_gravity)" in err
    assert main(base + ["--pixel", "-1"]) == 2
    assert "--pixel = -1" in capsys.readouterr().err
