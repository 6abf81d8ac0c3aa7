"""A stand-in ``regtrack`` command for the signal tests (tests/test_signals.py).

``sleepy`` runs :func:`regtrack.pipeline.workers.simulate_concurrently` with two views whose
worker (:func:`sleepy_worker`) opens a stage temporary in the cache, writes its pid next
to the cache and sleeps: the test then signals the command and checks that the workers
are gone, the temporaries removed and one line printed.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HELP = "test only: two sleeping view workers"


@dataclass
class FakeContext:
    cache: Any
    progress: Any = None
    timings: dict = field(default_factory=dict)
    sim_progress: Any = None
    produced: set = field(default_factory=set)

    def say(self, msg: str) -> None:
        pass


def sleepy_worker(ctx: FakeContext, mesh: Any, view: str) -> float:
    with ctx.cache.produce("simulate", view) as tmp:
        (tmp / "half.vtu").write_text("unfinished")
        (ctx.cache.root / f"pid-{view}").write_text(str(os.getpid()))
        time.sleep(300)
    return 0.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("cache")


def run(args: argparse.Namespace) -> int:
    from regtrack.pipeline import stages, workers
    from regtrack.pipeline.cache import StageCache

    stages.simulate_key = lambda ctx, key, view: view  # no case: the view names the stage
    ctx = FakeContext(StageCache(Path(args.cache)))
    (Path(args.cache) / "parent-ready").write_text(str(os.getpid()))
    workers.simulate_concurrently(ctx, stages.MeshOutput("mesh", Path(args.cache), None),
                                  ["CC", "MLO"], worker=sleepy_worker)
    return 0
