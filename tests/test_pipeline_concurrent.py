"""The views of a case simulated at the same time (``regtrack run`` on two or more cores):
:func:`regtrack.pipeline.workers.simulate_concurrently` with stand-in workers, so the
process pool, the error hand-back and the fallback are checked in seconds.  The real
simulations, and that they equal the serial ones, are checked end to end in
``tests/test_pipeline_run.py``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from regtrack.errors import SolverDidNotConvergeError
from regtrack.pipeline import stages, workers
from regtrack.pipeline.run import RunContext


class _Cache:
    """Stage-cache stand-in: the views listed as cached are hits (picklable)."""

    def __init__(self, cached=()):
        self.cached = set(cached)

    def lookup(self, stage, key):
        return Path("/cached") if key in self.cached else None


def _ok_or_fail(ctx, mesh, view):
    """Worker: CC fails as a real simulation would, MLO writes its marker file."""
    if view == "CC":
        raise SolverDidNotConvergeError("step 'compression': Newton did not converge beyond "
                                        "load fraction t = 0.5", load_fraction=0.5)
    Path(mesh, f"{view}.done").write_text(str(os.getpid()))
    return 1.0


def _die(ctx, mesh, view):
    """Worker: the process dies (out of memory, killed)."""
    os._exit(3)


@pytest.fixture
def ctx(monkeypatch):
    monkeypatch.setattr(stages, "simulate_key", lambda ctx, mesh_key, view: view)
    msgs: list[str] = []
    c = RunContext(case=None, configs=None, cache=_Cache(), progress=msgs.append)
    c.msgs = msgs
    return c


class _Mesh(str):
    key = "mesh"


def test_a_failed_view_is_handed_back_and_the_other_one_is_kept(ctx, tmp_path):
    mesh = _Mesh(str(tmp_path))
    failed = workers.simulate_concurrently(ctx, mesh, ["CC", "MLO"], worker=_ok_or_fail)
    assert list(failed) == ["CC"]
    assert isinstance(failed["CC"], SolverDidNotConvergeError)
    assert "t = 0.5" in str(failed["CC"])
    # MLO ran in another process while CC failed
    pid = int((tmp_path / "MLO.done").read_text())
    assert pid != os.getpid()
    assert any("at the same time (2 processes)" in m for m in ctx.msgs)
    assert any(m == "simulate CC: failed" for m in ctx.msgs)


def test_nothing_runs_concurrently_with_fewer_than_two_views_to_simulate(ctx, tmp_path):
    ctx.cache = _Cache(cached={"CC"})
    mesh = _Mesh(str(tmp_path))
    assert workers.simulate_concurrently(ctx, mesh, ["CC", "MLO"], worker=_ok_or_fail) == {}
    assert not (tmp_path / "MLO.done").exists()  # left to the serial loop
    assert ctx.msgs == []


def test_a_dead_worker_leaves_its_view_to_the_serial_loop(ctx, tmp_path, caplog):
    mesh = _Mesh(str(tmp_path))
    assert workers.simulate_concurrently(ctx, mesh, ["CC", "MLO"], worker=_die) == {}
    assert "simulating it again in this process" in caplog.text
