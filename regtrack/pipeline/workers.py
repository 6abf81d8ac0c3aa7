"""The simulate stage of several views at the same time, one worker process each.

:func:`simulate_concurrently` runs :func:`regtrack.pipeline.stages.simulate_stage` of the
views not yet in the cache in a pool of spawned processes; the workers' log records and
increments travel back to the parent on one queue, so the console shows them as if the
views ran here.  The caller (:func:`regtrack.pipeline.run.run_stages`) then finds every
result in the cache.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Any

from regtrack.errors import RegtrackError
from regtrack.pipeline import stages

log = logging.getLogger(__name__)


def simulate_concurrently(ctx, mesh: stages.MeshOutput, views, *, worker=None) -> dict[str, Exception]:
    """Simulate the ``views`` that are not in the cache at the same time, one process each
    (they are independent), so that :func:`.stages.simulate_stage` then finds every one there.

    Returns the error of each view whose simulation failed; the caller raises it when it
    reaches that view, and the other views' results are in the cache by then (nothing is
    lost).  A worker that dies or cannot send its error back leaves its view to be
    simulated again in this process (logged).  Does nothing when fewer than two views
    need simulating.  ``worker(ctx, mesh, view)`` (tests): a picklable function run in
    each process instead of :func:`_simulate_worker`; it returns seconds.

    Why: the Newton solver of one simulation keeps the two cores of the benchmark machine
    only partly busy (its GMRES solves on a stored factorisation are single-threaded and
    memory-bound, 36 % of the CC compression).  Measured on the 9,496-node benchmark
    hemisphere (``pipelines/bench_protocols.py`` with and without ``--concurrent``, back
    to back, 2 cores): CC + MLO one after the other 180.2 s, at the same time 140.0 s
    (another pair: 146.9 and 128.6 s), the same Newton paths and forces (PARDISO in strict
    CNR mode, :mod:`regtrack.mechanics.linsolve`).
    """
    import concurrent.futures as cf
    import multiprocessing

    from regtrack._signals import check_interrupted, stop_pool

    keys = {v: stages.simulate_key(ctx, mesh.key, v) for v in views}
    todo = [v for v in views if ctx.cache.lookup("simulate", keys[v]) is None]
    if len(todo) < 2:
        return {}
    t0 = time.perf_counter()
    ctx.say(f"simulate {' and '.join(todo)} at the same time ({len(todo)} processes)")
    lite = dataclasses.replace(ctx, progress=None, timings={}, sim_progress=None)
    failed: dict[str, Exception] = {}
    mp = multiprocessing.get_context("spawn")
    reports = mp.Queue()  # the workers' increments and log records
    relay = threading.Thread(target=_relay, args=(reports, ctx), daemon=True)
    relay.start()
    pool = cf.ProcessPoolExecutor(max_workers=len(todo), mp_context=mp, initializer=_init_worker,
                                  initargs=(reports, ctx.sim_progress is not None))
    try:
        futures = {pool.submit(_in_worker, worker or _simulate_worker, lite, mesh, v): v
                   for v in todo}
        pending = set(futures)
        while pending:
            done, pending = cf.wait(pending, timeout=0.5, return_when=cf.FIRST_COMPLETED)
            check_interrupted()  # a Ctrl-C swallowed in a finaliser stops the wait here
            for fut in done:
                view = futures[fut]
                try:
                    seconds = fut.result()  # the worker said "finished" on the queue
                    ctx.produced.add(("simulate", keys[view]))
                    ctx.say(f"simulate {view}: done ({seconds:.0f} s)")
                except RegtrackError as exc:
                    failed[view] = exc
                    reports.put((view, None, 1.0, {}))  # after the worker's increments
                    ctx.say(f"simulate {view}: failed")
                except Exception as exc:  # a dead worker, an error that did not pickle
                    reports.put((view, None, 1.0, {}))
                    log.warning("simulate %s: the worker process failed (%s: %s); simulating "
                                "it again in this process", view, type(exc).__name__, exc)
        pool.shutdown(wait=True)  # the workers' last reports are on the queue before the end
    except BaseException:  # Ctrl-C, SIGTERM: stop the workers now, do not wait for them
        stop_pool(pool)
        raise
    finally:
        reports.put(None)
        relay.join(timeout=5)
        reports.close()
    stages.add_time(ctx, "simulate_concurrent", t0)
    return failed


#: in a worker process of :func:`simulate_concurrently`: the queue to the parent, and
#: whether the parent shows the increments
_REPORTS: Any = None
_SHOW_INCREMENTS = False


def _in_worker(fn, *args):
    """``fn(*args)`` in a pool worker; a SIGTERM (``SystemExit``, see
    :func:`regtrack._signals.init_worker`) ends the process once ``fn``'s ``finally`` blocks
    have removed its temporaries, instead of returning to the pool's loop (which catches
    every exception and would wait for more work)."""
    import os

    try:
        return fn(*args)
    except SystemExit as exc:
        os._exit(exc.code if isinstance(exc.code, int) else 1)


def _init_worker(reports, show_increments: bool) -> None:
    """Worker start-up: SIGINT ignored and SIGTERM a clean exit (:func:`regtrack._signals.
    init_worker`); log records go to the parent (which filters, scrubs and prints them
    once, like its own), and so do the increments when the parent shows them."""
    import logging.handlers

    from regtrack._signals import init_worker

    init_worker()

    global _REPORTS, _SHOW_INCREMENTS
    _REPORTS, _SHOW_INCREMENTS = reports, show_increments
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(logging.handlers.QueueHandler(reports))
    root.setLevel(logging.WARNING)


def worker_context(ctx):
    """``ctx`` in a worker process, its ``sim_progress`` sending the increments to the
    parent when the parent shows them (unchanged elsewhere)."""
    if _REPORTS is None or not _SHOW_INCREMENTS:
        return ctx
    reports = _REPORTS

    def relay(view, step, t, **info):
        reports.put((view, step, t, info))
    return dataclasses.replace(ctx, sim_progress=relay)


def _relay(reports, ctx) -> None:
    """Parent thread: hand the workers' reports on until ``None`` arrives."""
    while True:
        try:
            item = reports.get()
        except (EOFError, OSError):
            return
        if item is None:
            return
        if isinstance(item, logging.LogRecord):
            logging.getLogger(item.name).handle(item)
        elif ctx.sim_progress is not None:
            view, step, t, info = item
            ctx.sim_progress(view, step, t, **info)


def _simulate_worker(ctx, mesh: stages.MeshOutput, view: str) -> float:
    """One view's :func:`.stages.simulate_stage` in a worker process of
    :func:`simulate_concurrently`; its warnings and increments go to the parent
    (:func:`_init_worker`), scrubbed like the caller's."""
    from regtrack.privacy import scrub_logs

    if _REPORTS is None:  # not started by simulate_concurrently: print warnings here
        logging.basicConfig(level=logging.WARNING,
                            format=f"[{view}] %(levelname)s %(name)s: %(message)s")
    ctx = worker_context(ctx)
    t0 = time.perf_counter()
    with scrub_logs(ctx.ids):
        stages.simulate_stage(ctx, mesh, view)
    return time.perf_counter() - t0
