"""``regtrack validate CASE``: summary and exit 0 for a valid case, problems and exit 2
for a broken one, ``--shallow`` without opening the inputs.  Uses the synthetic case
builder of ``test_case.py``."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_case import build_case, snapshot, valid_doc, write_doc

from regtrack.cli import main


@pytest.fixture
def case_dir(tmp_path: Path) -> Path:
    return build_case(tmp_path / "synth01")


def test_valid_case_prints_summary(case_dir: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["validate", str(case_dir)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("case synth01: Synthetic test case")
    assert "40 x 30 px" in out and out.rstrip().endswith("OK")


def test_case_toml_path_is_accepted(case_dir: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["validate", str(case_dir / "case.toml")]) == 0
    assert "case synth01" in capsys.readouterr().out


def test_invalid_case_lists_every_problem_and_exits_2(case_dir: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    doc = valid_doc()
    doc["mechanics"]["nu"] = 0.5
    doc["views"]["CC"]["nipple_pix"] = doc["views"]["CC"].pop("nipple_px")
    (case_dir / "mammo" / "mlo.dcm").unlink()
    write_doc(case_dir, doc)
    before = snapshot(case_dir)
    assert main(["validate", str(case_dir)]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    lines = cap.err.strip().splitlines()
    assert lines[0] == f"{case_dir}: invalid case, 2 problem(s):"
    toml = case_dir / "case.toml"
    assert f"  error: {toml} [mechanics] nu = 0.5: must be < 0.5" in cap.err
    assert f"  error: {toml} [views.MLO] mammogram = 'mammo/mlo.dcm': file not found" in cap.err
    assert "  warning: " in cap.err and "did you mean 'nipple_px'?" in cap.err
    assert snapshot(case_dir) == before


def test_shallow_does_not_open_inputs(case_dir: Path, capsys: pytest.CaptureFixture) -> None:
    (case_dir / "mammo" / "cc.dcm").write_text("not a DICOM")  # only deep mode opens it
    assert main(["validate", "--shallow", str(case_dir)]) == 0
    assert "shallow" in capsys.readouterr().out
    assert main(["validate", str(case_dir)]) == 2
    assert "not a DICOM file" in capsys.readouterr().err


def test_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["validate", str(tmp_path / "nope")]) == 2
    assert "no such case folder" in capsys.readouterr().err
