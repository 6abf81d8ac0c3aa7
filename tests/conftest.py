"""Shared test fixtures.

Real data comes through one accessor, :func:`shared_data`, which skips the test with a
clear reason when ``../shared/data`` (or ``$REGTRACK_SHARED_DATA``) is absent.
Sources (cite when used): Pelicano et al., Sensors 2021 / PLoS One 2024 (label maps);
Deng et al. 2015, DigiBreast (CC mammogram); peers/ (CalculiX, FEBio, SfePy results).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("REGTRACK_SHARED_DATA", REPO.parent / "shared" / "data"))
SAMPLE_CASES = REPO / "sample_cases"
#: The pipeline's stage cache shared by the tests that run the pipeline on the bundled
#: phantom (meshes and simulations computed once for all of them).
PIPELINE_CACHE = Path(os.environ.get("REGTRACK_CACHE", REPO / ".regtrack-cache"))


def shared_data(*parts: str) -> Path:
    """Path inside ../shared/data; skip the calling test if it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not available: {p} (set REGTRACK_SHARED_DATA to the shared/data folder)")
    return p


@pytest.fixture
def shared():
    return shared_data


def stop_at_step(monkeypatch, step: str) -> None:
    """Make the mechanics' step solver fail at protocol step ``step`` (every other step
    is solved), as a step that cannot be balanced does: the error keeps the state at the
    step's start as its last balanced one."""
    from regtrack.errors import SolverDidNotConvergeError
    from regtrack.mechanics import minimise

    real = minimise.minimise_step

    def failing(problem, u0, *, step_name="", **kw):
        if step_name == step:
            raise SolverDidNotConvergeError("no equilibrium at t = 0.5 (largest residual at node 7)",
                                            load_fraction=0.25, last_converged=u0)
        return real(problem, u0, step_name=step_name, **kw)

    monkeypatch.setattr(minimise, "minimise_step", failing)


#: Set in the child pytest of an ``isolated`` test (see :func:`pytest_pyfunc_call`).
_CHILD = "REGTRACK_ISOLATED_TEST_CHILD"


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """Run tests marked ``isolated`` in a fresh pytest process.

    The study-engine tests start real process pools in the test process, one of which
    loses a worker on purpose.  In the full suite the CI run then died, two tests on, of
    a broken pipe on pytest's own output (twice, at the same place, not reproduced with
    the study files alone): a file descriptor that pytest's capture had re-used was closed
    under it.  In a child process whatever the pools leave behind dies with the child.
    """
    import re
    import subprocess
    import sys

    if pyfuncitem.get_closest_marker("isolated") is None or os.environ.get(_CHILD) == "1":
        return None
    env = {**os.environ, _CHILD: "1"}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
                           pyfuncitem.nodeid], cwd=pyfuncitem.config.rootpath, env=env,
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=3600)
    if proc.returncode != 0:
        pytest.fail(f"isolated run of {pyfuncitem.nodeid} failed (exit {proc.returncode}):\n"
                    + (proc.stdout + proc.stderr)[-6000:], pytrace=False)
    skipped = re.search(r"^SKIPPED \[\d+\] [^\n]*?: (.*)$", proc.stdout, re.M)
    if skipped and " passed" not in proc.stdout.strip().splitlines()[-1]:
        pytest.skip(skipped.group(1))  # a skip in the child is a skip here, not a pass
    return True
