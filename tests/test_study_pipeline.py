"""Acceptance of issue 8 on the real pipeline: 2 cases x 2 c1 x 1 nu, coarse meshes, run
locally and on a ``dask.distributed`` LocalCluster started here (address passed on the
command line); the two tables must agree.

The claim is the equality of the two executors, not the values of c1: two values (the
issue asked for three) keep what the grid exercises, more than one run per case (the
second run of a case waits for the first to mesh, then shares its mesh) and two runs per
worker, at two thirds of the simulations.  The value left out is the softest, c1 = 0.3 kPa
(the largest sag under gravity).  The Dask run starts from the local run's
meshes (the stage cache's ``mesh`` folder copied; gmsh is deterministic) and simulates,
projects and registers every run itself.

Sample cases: the two bundled synthetic phantoms with simulated CC mammograms,
phantom01 (right breast) and phantom02 (left breast, another seed and tumour), so the
study covers both lateralities and every row has BS_Av/TS_Av (Figure 8).  Coarse patient
models (``target_nodes = 1500``, as the cases' own case.toml) keep it to minutes; at 1000
nodes phantom01's CC compression with c1 = 0.54 kPa did not converge and the runs were no
faster.
Tolerance: the tables are compared cell by cell, text for text, and numbers to a relative
1e-9 (last-bit noise of a multithreaded sparse solver is allowed; anything physical is
not).
"""

from __future__ import annotations

import math
import shutil
import tomllib

import pytest

from regtrack.cli import main
from regtrack.study.results import read_csv
from regtrack.study.spec import case_id_of
from tests.conftest import SAMPLE_CASES

pytestmark = pytest.mark.slow

STUDY = """
[study]
name = "acceptance"
views = ["CC"]
outputs = ["csv", "figure8", "pdf"]
workers = 2
[cases]
paths = ["{a}", "{b}"]
[parameters]
c1 = [0.54, 1.0]
nu = [0.49]
[overrides.model]
target_nodes = 1500
"""


@pytest.mark.isolated  # a LocalCluster and real pools: in a child pytest (conftest.py)
def test_real_pipeline_local_equals_dask(tmp_path):
    pytest.importorskip("regtrack.pipeline.run", reason="regtrack.pipeline.run.run_case not built yet")
    distributed = pytest.importorskip("distributed")
    cases = [SAMPLE_CASES / "phantom01", SAMPLE_CASES / "phantom02"]
    for c in cases:
        # Figure 8 plots BS_Av/TS_Av, which need a mammogram of the view
        assert "CC" in tomllib.loads((c / "case.toml").read_text()).get("views", {}), c
    p = tmp_path / "s.toml"
    p.write_text(STUDY.format(a=cases[0], b=cases[1]))
    rc_local = main(["-q", "study", str(p), "--out", str(tmp_path / "local"), "--no-progress"])
    shutil.copytree(tmp_path / "local" / "cache" / "mesh", tmp_path / "dask" / "cache" / "mesh")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        rc_dask = main(["-q", "study", str(p), "--out", str(tmp_path / "dask"), "--no-progress",
                        "--scheduler", cluster.scheduler_address])
    local = read_csv(tmp_path / "local" / "table.csv")
    dask = read_csv(tmp_path / "dask" / "table.csv")
    assert rc_local == 0, [r["error"] for r in local if r["status"] != "ok"]
    assert rc_dask == 0
    assert len(local) == 2 * 2 and [list(r) for r in local] == [list(r) for r in dask]
    for a, b in zip(local, dask):
        for k in a:
            if isinstance(a[k], float) and isinstance(b[k], float):
                assert math.isclose(a[k], b[k], rel_tol=1e-9, abs_tol=1e-12), (k, a[k], b[k])
            else:
                assert a[k] == b[k], k
    for r in local:
        for m in ("BS_Av", "D"):
            assert r.get(m) is not None and math.isfinite(r[m]), (r["case_id"], m)
    # the phantoms' DICOM PatientID is their case id, so the study names them by the
    # pipeline's pseudonym (regtrack.privacy), as regtrack run does
    ids = [case_id_of(c) for c in cases]
    assert all(i.startswith("anon-") for i in ids) and len(set(ids)) == 2
    assert {r["case_id"] for r in local} == set(ids)
    for c in ids:
        assert (tmp_path / "local" / f"figure8_{c}_CC.png").is_file()
