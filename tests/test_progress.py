"""Progress inside the simulations and warnings once each (issue 53): the increment hook,
its relay from the worker processes of ``simulate_concurrently``, the CLI's console
helpers, and console paths named as the user gave them."""

from __future__ import annotations

import logging

import pytest

from regtrack.cli._console import IncrementLines, OnceFilter, SimulationProgress, increment_text
from regtrack.pipeline import stages, workers
from regtrack.pipeline.run import RunContext
from regtrack.privacy import Identifiers


def _ctx(**kw) -> RunContext:
    return RunContext(case=None, configs=None, cache=None, **kw)


def test_the_increment_hook_numbers_the_increments_of_each_step():
    seen = []
    hook = stages.increment_hook(_ctx(sim_progress=lambda *a, **k: seen.append((a, k))), "CC")
    for step, t in (("gravity", 0.25), ("gravity", 1.0), ("compression", 0.1),
                    ("compression", 0.05), ("compression", 0.4)):  # a retry restarts at 0.05
        hook(step, t)
    hook("compression", 1.0, D=0.38, force_N=43.6)  # what a solver may add
    assert [k["increment"] for _, k in seen] == [1, 2, 1, 1, 2, 3]
    assert seen[-1] == (("CC", "compression", 1.0), {"increment": 3, "D": 0.38, "force_N": 43.6})
    seen.clear()  # within an increment: numbered as the next one, not counted
    hook("compression", 1.0, working_to=1.0, newton=4, updates=0)
    hook("compression", 1.0, working_to=1.0, newton=5, updates=1)
    hook("compression", 1.0)
    assert [k["increment"] for _, k in seen] == [4, 4, 4]
    assert stages.increment_hook(_ctx(), "CC") is None  # nobody listens: the solver gets None


def test_increment_text_shows_what_the_solver_reported():
    assert increment_text("compression", 0.5312, {"increment": 12}) == "increment 12 · t 0.53"
    assert (increment_text("compression", 1.0, {"increment": 3, "D": 0.312, "force_N": 22.44})
            == "increment 3 · t 1.00 · D 31.2 % · F 22.4 N")
    assert increment_text("gravity", 0.5, {"force_N": -1e-9}) == "t 0.50 · F 0.0 N"
    assert (increment_text("compression", 0.531, {"increment": 13, "working_to": 0.5725,
                                                   "newton": 37, "updates": 2})
            == "increment 13 · t 0.53 -> 0.57 · Newton iteration 37 · contact update 2")
    assert (increment_text("gravity", 0.25, {"working_to": 0.5, "newton": 1, "updates": 0})
            == "t 0.25 -> 0.50 · Newton iteration 1")


def test_each_warning_is_shown_once():
    f = OnceFilter()
    rec = [logging.LogRecord("regtrack.x", lvl, __file__, 1, msg, None, None)
           for lvl, msg in ((logging.WARNING, "a"), (logging.WARNING, "a"), (logging.WARNING, "b"),
                            (logging.INFO, "i"), (logging.INFO, "i"))]
    assert [f.filter(r) for r in rec] == [True, False, True, True, True]


def test_the_live_lines_come_and_go():
    from rich.console import Console

    console = Console(file=open("/dev/null", "w"), force_terminal=False)
    with SimulationProgress(console) as p:
        p.increment("CC", "compression", 0.5, increment=4)
        assert len(p.bar.tasks) == 1 and p.bar.tasks[0].completed == 0.5
        p.increment("CC", None, 1.0)
        assert p.bar.tasks == [] and p.tasks == {}


class _Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_without_a_terminal_a_long_step_writes_a_plain_line_now_and_then():
    """Every increment_line_s seconds per view, counted from its first increment: a short
    simulation writes nothing, a long one a line per interval; each view has its own."""
    clock, out = _Clock(), []
    lines = IncrementLines(out.append, interval_s=15.0, clock=clock)
    for dt, view, t in ((0, "CC", 0.1), (5, "CC", 0.2), (0, "MLO", 0.1), (11, "CC", 0.3),
                        (4, "CC", 0.4), (12, "CC", 0.5), (0, "MLO", 0.2)):
        clock.now += dt
        lines(view, "compression", t, {"increment": int(10 * t), "D": 0.3})
    assert out == ["CC compression · increment 3 · t 0.30 · D 30.0 %",
                   "CC compression · increment 5 · t 0.50 · D 30.0 %",
                   "MLO compression · increment 2 · t 0.20 · D 30.0 %"]
    lines("CC", None, 1.0, {})  # finished: a next simulation of the view starts afresh
    clock.now += 100
    lines("CC", "gravity", 0.25, {})
    assert len(out) == 3


@pytest.mark.parametrize("terminal", [False, True])
def test_plain_increment_lines_only_without_a_terminal(tmp_path, terminal):
    from rich.console import Console

    log, clock = tmp_path / "run.log", _Clock()
    with open(log, "w") as fh, SimulationProgress(Console(file=fh, force_terminal=terminal),
                                                  clock=clock) as p:
        p.increment("CC", "compression", 0.1, increment=1)
        clock.now += 20
        p.increment("CC", "compression", 0.6, increment=9, D=0.31, force_N=12.5)
    text = log.read_text()
    assert ("CC compression · increment 9 · t 0.60 · D 31.0 % · F 12.5 N" in text) != terminal


def test_the_simulate_command_logs_increments_without_a_terminal(caplog):
    """``regtrack simulate`` in a log file: the same plain lines, with the seconds since
    the start (pytest's stderr is not a terminal)."""
    from regtrack.cli.simulate import _progress

    clock = _Clock()
    with caplog.at_level(logging.INFO, logger="regtrack.simulate"), _progress(clock=clock) as update:
        update("compression", 0.1, D=0.05)
        clock.now += 16
        update("compression", 0.5, D=0.2, force_N=3.0)
    assert [r.getMessage() for r in caplog.records] == ["compression · t 0.50 · D 20.0 % · F 3.0 N (16 s)"]


def test_a_stage_line_is_not_wrapped_in_a_log_file(tmp_path):
    """A stage line longer than the console's width (80 columns without a terminal) is
    written on one line."""
    from rich.console import Console

    log = tmp_path / "run.log"
    msg = "register CC (paper mode): golden-section search of the in-plane rotation " * 2
    with open(log, "w") as fh, SimulationProgress(Console(file=fh, force_terminal=False)) as p:
        p.say(msg)
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    assert len(lines) == 1 and msg.strip() in lines[0]


class _Cache:
    def lookup(self, stage, key):
        return None


class _Mesh(str):
    key = "mesh"


def _reporting_worker(ctx, mesh, view):
    """Worker: two increments, a warning and the end, as simulate_stage in a worker sends."""
    ctx = workers.worker_context(ctx)
    ctx.sim_progress(view, "compression", 0.5, increment=1)
    ctx.sim_progress(view, "compression", 1.0, increment=2, D=0.38)
    logging.getLogger("regtrack.test").warning("%s: solver warning", view)
    ctx.sim_progress(view, None, 1.0)
    return 1.0


def test_workers_relay_increments_and_warnings(monkeypatch, caplog):
    monkeypatch.setattr(stages, "simulate_key", lambda ctx, mesh_key, view: view)
    seen, msgs = [], []
    ctx = _ctx(progress=msgs.append, sim_progress=lambda *a, **k: seen.append((a, k)))
    ctx.cache = _Cache()
    with caplog.at_level(logging.WARNING):
        assert workers.simulate_concurrently(ctx, _Mesh("/tmp"), ["CC", "MLO"],
                                            worker=_reporting_worker) == {}
    for v in ("CC", "MLO"):
        mine = [a for a, _ in seen if a[0] == v]
        # in the worker's order, the end last (its line goes)
        assert mine == [(v, "compression", 0.5), (v, "compression", 1.0), (v, None, 1.0)]
        assert f"simulate {v}: done (1 s)" in msgs
    assert sorted(r.getMessage() for r in caplog.records
                  if r.name == "regtrack.test") == ["CC: solver warning", "MLO: solver warning"]
    # simulate_stage then finds them in the cache without saying so a second time
    assert ctx.produced == {("simulate", "CC"), ("simulate", "MLO")}


@pytest.mark.parametrize("console, shown", [(True, "cases/p01/mammo/mlo.dcm"),
                                            (False, "<case>/mammo/mlo.dcm")])
def test_console_lines_name_files_as_the_user_gave_them(tmp_path, monkeypatch, console, shown):
    """Log records and progress lines (console) name the file as typed; output files keep
    the neutral label."""
    from regtrack.privacy import identifiers_of_case_folder

    case = tmp_path / "cases" / "p01"
    case.mkdir(parents=True)
    (case / "case.toml").write_text('[case]\nid = "x"\n')
    monkeypatch.chdir(tmp_path)
    ids = identifiers_of_case_folder("cases/p01")
    assert ids.scrub(f"{case.resolve()}/mammo/mlo.dcm", console=console) == shown
    assert Identifiers().scrub("/a/b.dcm", console=console) == "/a/b.dcm"


def test_the_log_handlers_get_their_streams_back(capsys):
    import sys

    from rich.console import Console

    h = logging.StreamHandler(sys.stderr)
    logging.getLogger().addHandler(h)
    try:
        for terminal in (False, True):
            with SimulationProgress(Console(stderr=True, force_terminal=terminal)):
                pass
            assert h.stream is sys.stderr
    finally:
        logging.getLogger().removeHandler(h)


@pytest.mark.parametrize("quiet", [True, False])
def test_run_is_quiet_under_q(monkeypatch, capsys, tmp_path, quiet):
    """``regtrack -q run``: no stage lines, no live lines, no summary; warnings still."""
    import regtrack.pipeline.run as pr
    from regtrack.cli import main
    from tests.conftest import SAMPLE_CASES

    got = {}

    def fake_run_case(case, **kw):
        got.update(kw)
        if kw["progress"] is not None:
            kw["progress"]("mesh: found in the cache")
        return [{"view": "CC", "BS_Av": 56.8}]
    monkeypatch.setattr(pr, "run_case", fake_run_case)
    argv = ["-q"] * quiet + ["run", str(SAMPLE_CASES / "phantom01"), "--out", str(tmp_path)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert (got["progress"] is None and got["sim_progress"] is None) == quiet
    assert ("report written" in err) != quiet and ("found in the cache" in err) != quiet


def test_the_simulate_command_progress_takes_what_the_solver_reports():
    """``regtrack simulate``'s progress callback takes the solver's keywords (D, force);
    a callback without them stopped every case-level simulation (found by
    pipelines/bench_cohort.py)."""
    from regtrack.cli.simulate import _progress

    with _progress() as update:
        update("compression", 0.5)
        update("compression", 1.0, D=0.38, force_N=42.3)
