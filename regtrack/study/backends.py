"""Where runs execute: a local process pool (default) or an existing Dask cluster.

Both backends offer the same small interface to :class:`regtrack.study.engine.Engine`:
``capacity()``, ``submit(runner, spec, attempt)``, ``wait(futures)``,
``died(exc)``, ``recover()`` and ``close()``.

* :class:`LocalBackend`: :class:`concurrent.futures.ProcessPoolExecutor` with the
  ``spawn`` start method (safe with threads, numba and MKL in the parent), sized to the
  machine by :func:`default_workers`.  When a worker process dies the pool is *broken*:
  every run in flight gets :class:`~concurrent.futures.process.BrokenProcessPool`; the
  engine re-submits them on a fresh pool (``death_breaks_all = True``).
* :class:`DaskBackend`: ``distributed.Client(address)``.  The scheduler itself re-runs
  tasks of a dead worker (``distributed.scheduler.allowed-failures``) and raises
  :class:`distributed.KilledWorker` after that; ``retries=`` is passed to ``submit`` for
  exceptions escaping :func:`regtrack.study.runner.execute` (it catches the run's own).
  The workers must have regtrack (and the runner function's module) importable.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import os
from typing import Any

from regtrack.errors import ConfigError
from regtrack.study.runner import RunSpec, execute

log = logging.getLogger(__name__)

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def machine_cores() -> int:
    """CPU cores this process may use (affinity-aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_workers(*, memory_per_run_gb: float = 2.0) -> int:
    """Local pool size: ``min(cores, available memory / memory_per_run_gb)``, at least 1."""
    import psutil

    avail_gb = psutil.virtual_memory().available / 2**30
    return max(1, min(machine_cores(), int(avail_gb // memory_per_run_gb)))


def _init_worker(threads: int) -> None:
    """Worker initialiser: cap BLAS/numba threads so workers do not oversubscribe cores;
    leave Ctrl-C to the parent and clean up on SIGTERM (:mod:`regtrack._signals`)."""
    from regtrack._signals import init_worker

    init_worker()
    for var in THREAD_VARS:
        os.environ.setdefault(var, str(threads))


class LocalBackend:
    """A process pool on this machine; ``workers = 0`` sizes it to the machine."""

    name = "local"
    death_breaks_all = True

    def __init__(self, *, workers: int = 0, memory_per_run_gb: float = 2.0):
        self.workers = workers or default_workers(memory_per_run_gb=memory_per_run_gb)
        self._pool: cf.ProcessPoolExecutor | None = None
        self.pools_started = 0

    def _ensure(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            threads = max(1, machine_cores() // self.workers)
            self._pool = cf.ProcessPoolExecutor(
                max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker, initargs=(threads,))
            self.pools_started += 1
            log.debug("local pool of %d workers started (%d threads each)", self.workers, threads)
        return self._pool

    def capacity(self) -> int:
        return self.workers

    def submit(self, runner: Any, spec: RunSpec, attempt: int) -> cf.Future:
        """Start ``spec``.  A pool that broke after the engine last looked (a worker died
        while another run's result was being collected) refuses new work; the run then
        gets a future that already failed with that error, so the engine treats it like
        the other runs in flight of the broken pool (suspects, not charged; a race seen in
        a clean-clone CI run)."""
        try:
            return self._ensure().submit(execute, runner, spec)
        except cf.process.BrokenProcessPool as exc:
            failed: cf.Future = cf.Future()
            failed.set_exception(exc)
            return failed

    @staticmethod
    def wait(futures: list) -> set:
        done, _ = cf.wait(futures, return_when=cf.FIRST_COMPLETED)
        return done

    @staticmethod
    def died(exc: BaseException) -> bool:
        return isinstance(exc, cf.process.BrokenProcessPool)

    def recover(self) -> None:
        """Drop a broken pool; the next submit starts a fresh one."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def close(self, *, abort: bool = False) -> None:
        """Shut the pool down; ``abort`` (Ctrl-C, SIGTERM) stops the workers at once."""
        if self._pool is not None:
            if abort:
                from regtrack._signals import stop_pool

                stop_pool(self._pool)
            else:
                self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskBackend:
    """An existing Dask distributed cluster reached at ``address`` (``tcp://host:8786``)."""

    name = "dask"
    death_breaks_all = False

    def __init__(self, address: str, *, retries: int = 2, timeout_s: float = 30.0):
        try:
            from distributed import Client
        except ImportError:  # pragma: no cover - dask[distributed] is a dependency
            raise ConfigError("--scheduler: dask.distributed is not installed; "
                              "pip install 'dask[distributed]'") from None
        try:
            self.client = Client(address, timeout=timeout_s)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ConfigError(f"--scheduler {address}: cannot connect ({exc}); start a scheduler "
                              "('dask scheduler') or fix the address") from None
        self.address = address
        self.retries = retries
        self.workers = self.capacity()

    def capacity(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    def submit(self, runner: Any, spec: RunSpec, attempt: int) -> Any:
        return self.client.submit(execute, runner, spec, pure=False, retries=self.retries,
                                  key=f"regtrack-run-{spec.run_key}-{attempt}")

    @staticmethod
    def wait(futures: list) -> set:
        from distributed import wait

        return set(wait(futures, return_when="FIRST_COMPLETED").done)

    @staticmethod
    def died(exc: BaseException) -> bool:
        from distributed import KilledWorker

        return isinstance(exc, KilledWorker)

    def recover(self) -> None:
        pass

    def close(self, *, abort: bool = False) -> None:
        self.client.close()


def make_backend(*, scheduler: str | None, workers: int, memory_per_run_gb: float,
                 retries: int) -> LocalBackend | DaskBackend:
    """Dask when a scheduler address is given, else the local pool."""
    if scheduler:
        return DaskBackend(scheduler, retries=retries)
    return LocalBackend(workers=workers, memory_per_run_gb=memory_per_run_gb)
