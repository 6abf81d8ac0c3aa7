"""What the CLI shows while it works: stage lines, a live line per simulation, and each
warning once.

:class:`SimulationProgress` draws one rich progress line per view being simulated
(``CC  compression  [bar of t]  increment 12 · t 0.53 · D 31.2 % · F 22.4 N``) above
which stage lines and warnings scroll; :class:`OnceFilter` drops a warning already shown.
Where the console is not a terminal (a log file, a pipe, a batch job) no live line is
drawn, so :class:`IncrementLines` writes the same text as a plain line instead, at most
every ``INCREMENT_LINE_S`` seconds per view: a step that runs for minutes still shows
that it moves, and a short one adds nothing.  Nothing here is used under ``-q``.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import Any


class OnceFilter(logging.Filter):
    """Let each distinct warning (level and message) through once; other records pass."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[tuple[int, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        key = (record.levelno, record.getMessage())
        if key in self.seen:
            return False
        self.seen.add(key)
        return True


def increment_text(step: str, t: float, info: dict[str, Any]) -> str:
    """``increment 12 · t 0.53 · D 31.2 % · F 22.4 N`` (the parts the solver reported);
    for an increment being solved, ``increment 13 · t 0.53 -> 0.57 · Newton iteration 37 ·
    contact update 2``."""
    parts = []
    if info.get("increment") is not None:
        parts.append(f"increment {info['increment']}")
    if info.get("working_to") is not None:
        parts.append(f"t {t:.2f} -> {float(info['working_to']):.2f}")
        parts.append(f"Newton iteration {int(info.get('newton', 0))}")
        if info.get("updates"):
            parts.append(f"contact update {int(info['updates'])}")
        return " · ".join(parts)
    parts.append(f"t {t:.2f}")
    if info.get("D") is not None:
        parts.append(f"D {100 * float(info['D']):.1f} %")
    force = info.get("force_N", info.get("plate_force_N"))
    if force is not None:
        f = float(force)
        parts.append(f"F {0.0 if abs(f) < 0.05 else f:.1f} N")  # no "-0.0" off contact
    return " · ".join(parts)


#: Seconds between two plain increment lines of one view (:class:`IncrementLines`).
INCREMENT_LINE_S = 15.0


class IncrementLines:
    """Plain increment lines for a console that is not a terminal: ``emit(text)`` with
    ``"<view> <step> · increment 12 · t 0.53 · ..."`` once ``interval_s`` seconds have
    passed since the view's first increment or its last line (``clock``: seconds)."""

    def __init__(self, emit: Callable[[str], None], *, interval_s: float = INCREMENT_LINE_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.emit = emit
        self.interval_s = interval_s
        self.clock = clock
        self.last: dict[str, float] = {}

    def __call__(self, view: str, step: str | None, t: float, info: dict[str, Any]) -> None:
        if step is None:  # the view's simulation has finished
            self.last.pop(view, None)
            return
        now = self.clock()
        if now - self.last.setdefault(view, now) < self.interval_s:
            return
        self.last[view] = now
        self.emit(" ".join(p for p in (view, step) if p) + " · " + increment_text(step, t, info))


class SimulationProgress:
    """Stage lines and one live progress line per simulated view on ``console``.

    Use as a context manager; pass :meth:`say` as ``progress`` and :meth:`increment` as
    ``sim_progress`` to :func:`regtrack.pipeline.run.run_case`.  While it is active, the
    root logger's console handlers write through the live display (so warnings scroll
    above the progress lines instead of breaking them), each warning once.
    """

    def __init__(self, console, *, clock: Callable[[], float] = time.monotonic) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.console = console
        self.t0 = time.perf_counter()
        self.bar = Progress(TextColumn("[bold]{task.fields[view]:>4}"),
                            TextColumn("{task.description:<22}"), BarColumn(bar_width=24),
                            TextColumn("{task.fields[info]}"), TimeElapsedColumn(),
                            console=console, transient=True)
        self.tasks: dict[str, Any] = {}
        self.lines = None if console.is_terminal else IncrementLines(self.say, clock=clock)
        self.once = OnceFilter()
        self._streams: list[tuple[logging.StreamHandler, Any]] = []

    def __enter__(self) -> SimulationProgress:
        self.bar.start()
        for h in logging.getLogger().handlers:
            h.addFilter(self.once)
            live = self.console.file  # the live display's proxy of stderr on a terminal
            if (isinstance(h, logging.StreamHandler) and h.stream is not live
                    and h.stream in (sys.__stderr__, sys.stderr)):
                self._streams.append((h, h.stream))
                h.setStream(live)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.bar.stop()
        for h, old in self._streams:
            h.setStream(old)
        for h in logging.getLogger().handlers:
            h.removeFilter(self.once)

    def say(self, msg: str) -> None:
        """A stage line, with the seconds since the start; never wrapped (a log file or a
        pipe has no width, and a wrapped line splits a message a user greps for)."""
        self.console.print(f"[dim]{time.perf_counter() - self.t0:7.1f} s[/dim]  {msg}",
                           soft_wrap=True)

    def increment(self, view: str, step: str | None, t: float, **info: Any) -> None:
        """A converged increment of ``view``'s ``step`` at load fraction ``t``; ``step``
        None: the view's simulation has finished (its line goes).  Without a terminal, a
        plain line now and then (:class:`IncrementLines`)."""
        if self.lines is not None:
            self.lines(view, step, t, info)
        task = self.tasks.get(view)
        if step is None:
            if task is not None:
                self.bar.remove_task(task)
                del self.tasks[view]
            return
        if task is None:
            task = self.tasks[view] = self.bar.add_task(step, total=1.0, view=view, info="")
        self.bar.update(task, description=step, completed=min(max(t, 0.0), 1.0),
                        info=increment_text(step, t, info))
