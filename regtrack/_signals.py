"""Stopping cleanly on SIGINT (Ctrl-C) and SIGTERM.

Before issue 53, SIGTERM to ``regtrack run`` killed the parent without a word and left its
two view-simulation workers running, and SIGINT to the parent alone waited ~45 s in the
process pool's shutdown for the workers to finish.  Now:

* the command line turns SIGTERM into :class:`Terminated` (a ``KeyboardInterrupt``), so
  both signals unwind the same way: every ``finally`` runs, the stage being produced in a
  temporary ``.part`` folder is removed (:meth:`regtrack.pipeline.cache.StageCache.produce`),
  and the CLI prints one line;
* worker processes ignore SIGINT (a Ctrl-C reaches the whole process group; the parent
  decides) and turn SIGTERM into ``SystemExit``, so their own ``finally`` blocks remove
  their temporary folders too;
* :func:`stop_pool` terminates the workers of a process pool at once instead of waiting
  for them;
* what a SIGKILL leaves behind (``.part`` folders and files) is removed at the next start
  (:meth:`regtrack.pipeline.cache.StageCache.remove_stale`).
"""

from __future__ import annotations

import logging
import signal
from typing import Any

log = logging.getLogger(__name__)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated(signum)


def install_cli_handlers() -> None:
    """SIGTERM raises :class:`Terminated` in the main thread (SIGINT already raises
    ``KeyboardInterrupt``).  Call from the main thread only."""
    signal.signal(signal.SIGTERM, _raise_terminated)


def _exit_on_sigterm(signum: int, frame: Any) -> None:
    raise SystemExit(128 + signum)


def init_worker() -> None:
    """Process-pool initializer: ignore SIGINT, exit through ``SystemExit`` on SIGTERM."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit_on_sigterm)


def stop_pool(pool: Any, *, timeout_s: float = 10.0) -> int:
    """Terminate the worker processes of a :class:`concurrent.futures.ProcessPoolExecutor`
    and shut it down without waiting for its work; return how many were running.

    Each worker gets SIGTERM (it cleans up through ``SystemExit``); one still alive after
    ``timeout_s`` is killed.
    """
    procs = list((getattr(pool, "_processes", None) or {}).values())
    alive = [p for p in procs if p.is_alive()]
    for p in alive:
        p.terminate()
    pool.shutdown(wait=False, cancel_futures=True)
    for p in alive:
        p.join(timeout_s)
        if _running(p.pid):  # the pool's own thread may have reaped it meanwhile
            log.warning("worker process %d did not stop on SIGTERM; killing it", p.pid)
            p.kill()
            p.join(timeout_s)
    return len(alive)


def _running(pid: int) -> bool:
    """Whether process ``pid`` still runs (not gone, not a zombie waiting to be reaped)."""
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:  # no /proc: trust kill(0)
        return True
