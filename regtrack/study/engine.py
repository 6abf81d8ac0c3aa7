"""The study engine: cached runs, shared-work scheduling, retries and failure records.

:class:`Engine` takes a list of :class:`~regtrack.study.runner.RunSpec` and

1. loads every run already in the result cache (:class:`~regtrack.study.results.ResultCache`)
   and computes only the others, so an interrupted study resumes where it stopped;
2. starts runs so that work they share is done once: a run is started only when, for
   each of its share groups (same case mesh; same simulation), a run of that group has
   finished or none is in flight.  The first run of a case builds the mesh into the
   stage cache; the others then find it there instead of meshing concurrently.
3. records a failing run (its error, type and traceback) and goes on; a run whose worker
   process died is re-submitted up to ``retries`` times, then recorded as failed.

The backend (local pool or Dask) is started lazily, only when something needs computing,
and kept across :meth:`Engine.run` calls (calibration evaluates points one by one).
"""

from __future__ import annotations

import logging
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from regtrack.study.backends import LocalBackend, make_backend
from regtrack.study.results import ResultCache
from regtrack.study.runner import FAILED, RunSpec

log = logging.getLogger(__name__)

RESULTS_SUBDIR = "study-runs"


@dataclass
class Execution:
    """What one :meth:`Engine.run` did.  Lists hold run keys."""

    outcomes: dict[str, dict] = field(default_factory=dict)
    cached: list[str] = field(default_factory=list)
    computed: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    retried: int = 0
    seconds: float = 0.0
    backend: str = "none"
    workers: int = 0

    @property
    def hit_rate(self) -> float:
        """Fraction of runs found in the result cache."""
        n = len(self.cached) + len(self.computed)
        return len(self.cached) / n if n else 0.0


class _Progress:
    """Rich progress bar: runs done / failed / cached / remaining with an ETA."""

    def __init__(self, *, enabled: bool, label: str, total: int, cached: int):
        self.bar = None
        self.counts = Counter(cached=cached)
        self.total = total
        if not enabled or total == 0:
            return
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                   TimeElapsedColumn, TimeRemainingColumn)

        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                            MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
                            TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())
        self.bar.start()
        self.task = self.bar.add_task(label, total=total, status=self._status())

    def _status(self) -> str:
        c = self.counts
        remaining = self.total - c["ok"] - c["failed"]
        return (f"done {c['ok']} failed {c['failed']} remaining {remaining} "
                f"(cached {c['cached']}, retried {c['retried']})")

    def update(self, event: str) -> None:
        self.counts[event] += 1
        if self.bar is not None:
            adv = 1 if event in ("ok", "failed") else 0
            self.bar.update(self.task, advance=adv, status=self._status())

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _died_record(spec: RunSpec, exc: BaseException, attempts: int) -> dict:
    return {"run_key": spec.run_key, "status": FAILED, "rows": [],
            "error": f"worker process died {attempts} time(s) running this case "
                     f"({type(exc).__name__}: {' '.join(str(exc).split())}); it may run out of "
                     "memory: lower [study] workers or raise memory_per_run_gb",
            "error_type": "WorkerDied", "deterministic": False,
            "traceback": None, "seconds": None, "host": None, "pid": None}


def _error_record(spec: RunSpec, exc: BaseException) -> dict:
    return {"run_key": spec.run_key, "status": FAILED, "rows": [],
            "error": " ".join(str(exc).split()) or type(exc).__name__,
            "error_type": type(exc).__name__, "deterministic": False,
            "traceback": "".join(traceback.format_exception(exc)), "seconds": None,
            "host": None, "pid": None}


class Engine:
    """Execute runs through a backend with the result cache in ``cache_dir/study-runs``.

    Parameters
    ----------
    runner : str
        Name of a registered runner (see :func:`regtrack.study.runner.known_runners`);
        resolved here, in the parent process, and the function handed to the workers.
    cache_dir : Path
        Cache root shared with the pipeline's stage cache.
    scheduler : str, optional
        Dask scheduler address; None runs a local process pool.
    workers : int
        Local pool size, 0 = sized to the machine (ignored with a scheduler).
    retries : int
        Re-submissions of a run whose worker died.
    retry_failed : bool
        Recompute runs whose failure is cached (after fixing a case, say).
    progress : bool
        Show a rich progress bar.
    """

    def __init__(self, *, runner: str, cache_dir: Path, scheduler: str | None = None,
                 workers: int = 0, memory_per_run_gb: float = 2.0, retries: int = 2,
                 retry_failed: bool = False, progress: bool = True):
        from regtrack.study.runner import resolve_runner

        self.runner = runner
        self.runner_fn = resolve_runner(runner)  # ConfigError for an unknown name, before any work
        self.cache = ResultCache(Path(cache_dir) / RESULTS_SUBDIR)
        self.scheduler = scheduler
        self.workers = workers
        self.memory_per_run_gb = memory_per_run_gb
        self.retries = retries
        self.retry_failed = retry_failed
        self.progress = progress
        self._backend: LocalBackend | object | None = None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, exc_type: type | None, *exc: object) -> None:
        self.close(abort=exc_type is not None and issubclass(exc_type, KeyboardInterrupt))

    def close(self, *, abort: bool = False) -> None:
        """Shut the backend down; ``abort`` (Ctrl-C, SIGTERM) stops the workers at once."""
        if self._backend is not None:
            self._backend.close(abort=abort)  # type: ignore[attr-defined]
            self._backend = None

    def backend(self):
        if self._backend is None:
            self._backend = make_backend(scheduler=self.scheduler, workers=self.workers,
                                         memory_per_run_gb=self.memory_per_run_gb,
                                         retries=self.retries)
        return self._backend

    def run(self, runs: list[RunSpec], *, label: str = "study") -> Execution:
        """Outcomes of ``runs`` (cached or computed); never raises for a failing run."""
        t0 = time.perf_counter()
        ex = Execution()
        pending: list[RunSpec] = []
        done_groups: set[str] = set()
        for spec in runs:
            if spec.run_key in ex.outcomes:
                continue
            out = self.cache.load(spec.run_key, retry_failed=self.retry_failed)
            if out is None:
                if all(p.run_key != spec.run_key for p in pending):
                    pending.append(spec)
                continue
            ex.outcomes[spec.run_key] = out
            ex.cached.append(spec.run_key)
            done_groups.update(spec.groups)
        log.log(logging.INFO if len(runs) > 1 else logging.DEBUG,
                "%s: %d runs, %d cached, %d to compute", label, len(ex.cached) + len(pending),
                len(ex.cached), len(pending))
        if pending:
            prog = _Progress(enabled=self.progress and len(pending) > 1, label=label,
                             total=len(pending),
                             cached=len(ex.cached))
            try:
                self._compute(pending, done_groups, ex, prog)
            finally:
                prog.close()
            backend = self.backend()
            ex.backend = backend.name
            ex.workers = backend.workers
        ex.failed = [k for k, o in ex.outcomes.items() if o["status"] == FAILED]
        ex.seconds = time.perf_counter() - t0
        return ex

    def _compute(self, pending: list[RunSpec], done_groups: set[str], ex: Execution,
                 prog: _Progress) -> None:
        """Submit, collect and retry until every pending run has an outcome.

        Worker deaths on a local pool break the whole pool, so the culprit is unknown
        when several runs were in flight: they all become *suspects*, are not charged a
        retry, and are re-run one at a time; a death with a single run in flight is
        charged to that run.  An innocent run therefore never fails because of another.
        """
        backend = self.backend()
        inflight: dict[object, RunSpec] = {}
        busy: Counter[str] = Counter()
        attempts: Counter[str] = Counter()
        suspects: set[str] = set()
        while pending or inflight:
            self._fill(pending, inflight, busy, done_groups, suspects, attempts, backend)
            finished = backend.wait(list(inflight))
            batch = [(fut, inflight.pop(fut)) for fut in finished]
            results = [(spec, *self._result(fut, backend)) for fut, spec in batch]
            if backend.death_breaks_all and any(kind == "died" for _, kind, _ in results):
                # a broken local pool fails every run in flight: collect them, restart it
                rest = [(fut, inflight.pop(fut)) for fut in list(inflight)]
                results += [(spec, *self._result(fut, backend)) for fut, spec in rest]
                backend.recover()
            n_died = sum(kind == "died" for _, kind, _ in results)
            for spec, kind, value in results:
                busy.subtract(spec.groups)
                if kind == "died":
                    charged = n_died == 1 or not backend.death_breaks_all
                    out = self._died(spec, value, attempts, charged=charged)
                    if out is None:
                        if backend.death_breaks_all:
                            suspects.add(spec.run_key)
                        pending.insert(0, spec)
                        ex.retried += 1
                        prog.update("retried")
                        continue
                else:
                    out = value if kind == "ok" else _error_record(spec, value)
                suspects.discard(spec.run_key)
                self._record(spec, out, ex, prog)
                done_groups.update(spec.groups)

    def _fill(self, pending, inflight, busy, done_groups, suspects, attempts, backend) -> None:
        """Submit ready runs up to the backend's capacity (suspects alone, one at a time)."""
        if any(s.run_key in suspects for s in inflight.values()):
            return
        first_suspect = next((s for s in pending if s.run_key in suspects), None)
        if first_suspect is not None:
            if not inflight:
                pending.remove(first_suspect)
                inflight[backend.submit(self.runner_fn, first_suspect,
                                        attempts[first_suspect.run_key])] = first_suspect
                busy.update(first_suspect.groups)
            return
        i = 0
        while len(inflight) < backend.capacity() and i < len(pending):
            spec = pending[i]
            if all(g in done_groups or busy[g] == 0 for g in spec.groups):
                pending.pop(i)
                inflight[backend.submit(self.runner_fn, spec, attempts[spec.run_key])] = spec
                busy.update(spec.groups)
            else:
                i += 1

    @staticmethod
    def _result(fut, backend) -> tuple[str, object]:
        """``("ok", outcome)``, ``("died", exc)`` or ``("error", exc)`` of a finished future."""
        try:
            return "ok", fut.result()
        except Exception as exc:  # noqa: BLE001 - recorded, the study goes on
            return ("died" if backend.died(exc) else "error"), exc

    def _died(self, spec: RunSpec, exc, attempts: Counter, *, charged: bool) -> dict | None:
        """None to re-submit the run whose worker died, or its failure record."""
        if not charged:
            log.warning("a worker died with case %s (run %s) among the runs in flight; "
                        "re-running it alone", spec.case_id, spec.run_key)
            return None
        attempts[spec.run_key] += 1
        n = attempts[spec.run_key]
        if n <= self.retries:
            log.warning("worker died running case %s (run %s); retry %d of %d",
                        spec.case_id, spec.run_key, n, self.retries)
            return None
        return _died_record(spec, exc, n)

    def _record(self, spec: RunSpec, out: dict, ex: Execution, prog: _Progress) -> None:
        ex.outcomes[spec.run_key] = out
        ex.computed.append(spec.run_key)
        self.cache.store(out)
        if out["status"] == FAILED:
            log.info("run failed: case %s %s: %s: %s", spec.case_id, spec.params,
                        out.get("error_type"), out.get("error"))
            prog.update("failed")
        else:
            prog.update("ok")
