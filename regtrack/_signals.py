"""Stopping cleanly on SIGINT (Ctrl-C) and SIGTERM.

Before issue 53, SIGTERM to ``regtrack run`` killed the parent without a word and left its
two view-simulation workers running, and SIGINT to the parent alone waited ~45 s in the
process pool's shutdown for the workers to finish.  Now:

* the command line turns SIGTERM into :class:`Terminated` (a ``KeyboardInterrupt``), so
  both signals unwind the same way: every ``finally`` runs, the stage being produced in a
  temporary ``.part`` folder is removed (:meth:`regtrack.pipeline.cache.StageCache.produce`),
  and the CLI prints one line;
* an interrupt whose exception Python swallowed (it arrived while a finaliser ran) is
  raised again at the next stage line, stage commit or poll of the view workers
  (:func:`check_interrupted`), so a Ctrl-C is never lost and an interrupted stage is never
  stored;
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


#: The signal that asked the command line to stop (None: none).  Python swallows an
#: exception raised while a finaliser or a weakref callback runs ("Exception ignored in
#: ..."), so the exception of a signal handler that happens to run there is lost; the
#: signal is kept here, and :func:`check_interrupted` raises it again.
_pending: int | None = None


def _interrupt(signum: int) -> KeyboardInterrupt:
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


def _raise_interrupt(signum: int, frame: Any) -> None:
    global _pending
    _pending = signum
    raise _interrupt(signum)


def check_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` (or :class:`Terminated`) again if SIGINT or SIGTERM
    arrived since :func:`install_cli_handlers`, in case its first exception was swallowed.
    Called where work moves on (each stage line, each stage's commit to the cache, each
    poll of the view workers)."""
    if _pending is not None:
        raise _interrupt(_pending)


def install_cli_handlers() -> dict[int, Any]:
    """SIGINT raises ``KeyboardInterrupt`` and SIGTERM :class:`Terminated` in the main
    thread, and both are remembered for :func:`check_interrupted`.  Returns the previous
    handlers for :func:`restore_handlers`.  Call from the main thread only."""
    global _pending
    _pending = None
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in previous:
        signal.signal(s, _raise_interrupt)
    return previous


def restore_handlers(previous: dict[int, Any]) -> None:
    """Put back the handlers :func:`install_cli_handlers` replaced, and forget a pending
    interrupt (it has been handled)."""
    global _pending
    _pending = None
    for s, h in previous.items():
        signal.signal(s, h)


def _exit_on_sigterm(signum: int, frame: Any) -> None:
    """Exit through ``SystemExit`` once: a further SIGTERM is ignored, so that it cannot
    interrupt the ``finally`` blocks that remove the stage temporaries (the process pool
    terminates its remaining workers again when one of them has exited)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
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
