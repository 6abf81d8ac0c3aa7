"""gmsh for the length of a ``with`` block, leaving the process's signal handling as it was.

gmsh's C library sets SIGPIPE back to its default action (terminate) when it initialises,
and its Python API (``interruptible=True``, the default) sets SIGINT to the default action
and never restores it (gmsh 4.x: ``finalize`` reads a module global that ``initialize``
does not set).  A Python process that had meshed in-process then died of SIGPIPE where
Python raises ``BrokenPipeError`` (writing to the pipe of a process-pool worker that has
died), and of Ctrl-C without unwinding its ``finally`` blocks.  Every in-process use of
gmsh in regtrack goes through :func:`gmsh_session`.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

#: the signals whose handling gmsh changes
_SIGNALS = (signal.SIGINT, signal.SIGPIPE)


@contextmanager
def gmsh_session(*, threads: int | None = None) -> Iterator[Any]:
    """Initialise gmsh (no configuration files, no terminal output, ``threads`` threads when
    given), yield the ``gmsh`` module, finalise it, and put back the handlers of SIGINT and
    SIGPIPE after both.  Signal handlers can only be set from the main thread; elsewhere
    they are left as they are."""
    import gmsh

    main = threading.current_thread() is threading.main_thread()
    saved = {s: signal.getsignal(s) for s in _SIGNALS} if main else {}

    def restore() -> None:
        for s, handler in saved.items():
            if handler is not None:  # None: set outside Python, nothing to put back
                signal.signal(s, handler)

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        restore()
        gmsh.option.setNumber("General.Terminal", 0)
        if threads is not None:
            gmsh.option.setNumber("General.NumThreads", threads)
        yield gmsh
    finally:
        gmsh.finalize()
        restore()
