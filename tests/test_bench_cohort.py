"""The cohort benchmark's pieces (pipelines/bench_cohort.py) without running the cohort:
the case folder it writes loads as a case with the asked D, a child that overruns its
timeout is killed and recorded, and the per-view summary takes the median and the worst of
the completed runs only."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from regtrack.imaging.volume import LabelVolume, make_affine

BENCH = Path(__file__).resolve().parents[1] / "pipelines" / "bench_cohort.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_cohort", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop(spec.name, None)


@pytest.fixture
def src(tmp_path):
    """A small label map (a cube of tissue) for the case folders the benchmark writes."""
    from regtrack.imaging.readers import write_label_map

    d = np.zeros((8, 8, 8), np.int16)
    d[2:6, 2:6, 2:6] = 1
    path = tmp_path / "labels.nii.gz"
    write_label_map(LabelVolume(d, make_affine((0, 0, 0), (1, 1, 1))), path)
    return path


def test_case_folder_loads_with_the_asked_compression(bench, src, tmp_path):
    from regtrack.case import load_case
    case = load_case(bench.write_case(tmp_path / "c", case_id="exam99", labels=src, side="L", D=0.5), deep=False)
    assert case.id == "exam99" and case.mri.side == "L"
    assert case.override_table("protocol.CC")["target_D"] == 0.5
    assert case.override_table("protocol.MLO")["target_D"] == 0.5
    assert (tmp_path / "c" / "mri" / "labels.nii.gz").is_file() and not (tmp_path / "c" / "mri" / "labels.nii.gz").is_symlink()


def test_child_over_its_timeout_is_killed_and_recorded(bench, tmp_path, monkeypatch):
    # a stand-in for the Python interpreter whose every `-m regtrack.cli ...` run hangs
    hang = tmp_path / "hang.sh"
    hang.write_text("#!/bin/sh\nsleep 30\n")
    hang.chmod(0o755)
    monkeypatch.setattr(bench.sys, "executable", str(hang))
    r = bench.run_child(["mesh"], log=tmp_path / "x.log", timeout_s=0.5, threads=1)
    assert r.rc is None and "timeout" in r.error and r.wall_s < 10.0


def test_summary_is_median_and_worst_of_completed_runs(bench):
    rows = [{"view": "CC", "D_setting": "default", "completed": True, "wall_s": w, "force_balance_rel": f}
            for w, f in [(10.0, 1e-6), (30.0, 3e-3), (20.0, 2e-6)]]
    rows.append({"view": "CC", "D_setting": "default", "completed": False, "wall_s": 999.0, "force_balance_rel": None})
    (line,) = [ln for ln in bench.summary_lines(rows, ["view", "D_setting"]) if ln.startswith("| CC")]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[2] == "3 of 4"
    assert "20.0 / 30.0" in cells  # wall: median and worst, the failed run left out
    assert "0.0002 % / 0.3 %" in cells


def test_settings_reach_every_case_and_bad_ones_are_named(bench, src, tmp_path):
    """``--settings``: the cohort off the defaults (e.g. the self-contact barrier on) with
    the same table; a file that does not parse, or that sets what the benchmark writes
    itself, is refused in one line naming the file."""
    from regtrack.case import load_case
    f = tmp_path / "barrier.toml"
    f.write_text("[contact]\nself_contact_gap_mm = 0.5\n")
    settings = bench.read_settings(f)
    case = load_case(bench.write_case(tmp_path / "c", case_id="exam99", labels=src, side="L", D=0.5,
                                      settings=settings), deep=False)
    assert case.override_table("contact")["self_contact_gap_mm"] == 0.5
    assert case.override_table("protocol.CC")["target_D"] == 0.5
    assert bench.read_settings(None) == ""
    for text, word in [("[contact\n", "not TOML"), ("[protocol.CC]\ntarget_D = 0.3\n", "[protocol]")]:
        f.write_text(text)
        with pytest.raises(ValueError, match=word) as err:
            bench.read_settings(f)
        assert str(f) in str(err.value) and "\n" not in str(err.value)
