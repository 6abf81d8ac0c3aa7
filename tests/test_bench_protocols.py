"""The protocol benchmark's reference iteration (pipelines/bench_protocols.py) runs on a
model and gives a time: a smoke test against the mechanics API it drives (the figure
itself is a measurement, printed by the benchmark, never asserted)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

from regtrack.mechanics.meshes import hemisphere_model

BENCH = Path(__file__).resolve().parents[1] / "pipelines" / "bench_protocols.py"


def test_reference_iteration_runs_on_a_hemisphere():
    spec = importlib.util.spec_from_file_location("bench_protocols", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    model = hemisphere_model(50.0, 9.0, tumour_radius=8.0)
    t = mod.reference_iteration(model, repeats=2)
    assert math.isfinite(t) and t > 0.0
