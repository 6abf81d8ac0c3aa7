"""End-to-end `regtrack run` on the bundled real-geometry case (Pelicano et al., Sensors
2021 / PLoS One 2024: sample_cases/pelicano_exam03, a cropped real label map).

The case has no mammograms, so the run stops after the virtual mammograms and says so;
this exercises mesh -> CC and MLO simulations -> projection -> report on real geometry.
A coarse mesh keeps it within a few minutes on 2 cores.
"""

from __future__ import annotations

import json
import shutil

import pytest

from regtrack.pipeline.run import run_case
from tests.conftest import SAMPLE_CASES


pytestmark = pytest.mark.slow



def test_run_without_mammograms_simulates_and_reports(tmp_path):
    msgs: list[str] = []
    out = tmp_path / "out"
    rows = run_case(SAMPLE_CASES / "pelicano_exam03", overrides={"model": {"target_nodes": 1500}},
                    cache_dir=tmp_path / "cache", out_dir=out, progress=msgs.append,
                    concurrent=True)
    assert [r["view"] for r in rows] == ["CC", "MLO"]
    assert any("simulate CC and MLO at the same time" in m for m in msgs)
    # the shipped protocols' targets (paper: CC 38 %, MLO 28 %) are reached exactly: the
    # upper plate is driven to the gap (1 - D) T0
    assert rows[0]["D"] == pytest.approx(0.38, abs=1e-6)
    assert rows[1]["D"] == pytest.approx(0.28, abs=1e-6)
    for r in rows:
        assert r["force_N"] > 0
        assert r["max_penetration_mm"] < 0.1  # the contact guard rail (issue 5)
        assert "BS_Av" not in r  # no real mammogram, no registration metrics
    assert any("no real mammograms" in m for m in msgs)
    doc = json.loads((out / "metrics.json").read_text())
    assert len(doc["views"]) == 2
    for v in ("cc", "mlo"):
        assert (out / v / "virtual.png").read_bytes()[:4] == b"\x89PNG"
        assert json.loads((out / v / "virtual.json").read_text())["view"] == v.upper()
    assert (out / "report.pdf").read_bytes()[:5] == b"%PDF-"
    # a re-run re-uses the mesh and both simulations from the cache
    msgs.clear()
    run_case(SAMPLE_CASES / "pelicano_exam03", overrides={"model": {"target_nodes": 1500}},
             cache_dir=tmp_path / "cache", out_dir=None, progress=msgs.append)
    assert sum("found in the cache" in m for m in msgs) == 3
    # the views simulated one after the other give the very same results (PARDISO in
    # strict CNR mode, the element kernel's sums in serial order: the Newton path does not
    # depend on the threads or on the other process).  The claim is about the simulations:
    # the serial run starts from the same mesh (its cache folder copied; the mesher is
    # deterministic anyway) and simulates both views afresh
    shutil.copytree(tmp_path / "cache" / "mesh", tmp_path / "cache-serial" / "mesh")
    msgs.clear()
    serial = run_case(SAMPLE_CASES / "pelicano_exam03", overrides={"model": {"target_nodes": 1500}},
                      cache_dir=tmp_path / "cache-serial", out_dir=None, progress=msgs.append,
                      concurrent=False)
    assert not any("at the same time" in m for m in msgs)
    assert sum("found in the cache" in m for m in msgs) == 1  # the mesh; both views simulated
    assert serial == rows


def test_a_stopped_simulation_keeps_its_balanced_steps_outside_the_cache(tmp_path, monkeypatch):
    """The stage cache computes a simulation in a temporary folder that is removed when
    the stage fails; a view that stops must still keep the steps balanced before it, in
    the file its error names (``<cache>/simulate/<key>.stopped/``), and that folder is
    never taken for a cached result."""
    import re
    from pathlib import Path

    from regtrack.errors import SolverDidNotConvergeError
    from tests.conftest import stop_at_step

    stop_at_step(monkeypatch, "standing-gravity")
    with pytest.raises(SolverDidNotConvergeError) as err:
        run_case(SAMPLE_CASES / "pelicano_exam03", overrides={"model": {"target_nodes": 1500}},
                 views=("CC",), cache_dir=tmp_path / "cache", out_dir=tmp_path / "out",
                 concurrent=False)
    kept = Path(re.search(r"are kept in (\S+\.vtu)", str(err.value)).group(1))
    assert kept.is_file() and kept.parent.name.endswith(".stopped")
    doc = json.loads(kept.with_suffix(".json").read_text())
    assert [s["name"] for s in doc["steps"]] == ["gravity-unloading", "lower-plate-contact"]
    assert not list((tmp_path / "cache" / "simulate").glob(".*.part*"))
    # the next run does not take the stopped folder for a result: it simulates again
    msgs: list[str] = []
    with pytest.raises(SolverDidNotConvergeError):
        run_case(SAMPLE_CASES / "pelicano_exam03", overrides={"model": {"target_nodes": 1500}},
                 views=("CC",), cache_dir=tmp_path / "cache", out_dir=tmp_path / "out",
                 concurrent=False, progress=msgs.append)
    assert any("simulate CC: cc protocol" in m for m in msgs)
