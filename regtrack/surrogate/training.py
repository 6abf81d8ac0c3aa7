"""Training and validation simulations of one case's view, and the surrogate built on them.

Each design point becomes the case's overrides (:func:`regtrack.study.params.apply_point`:
``c1`` sets ``[mechanics] tissue_c1_kpa`` and the homogeneous tissue model, ``nu``,
``target_D`` of the view, ``friction``) and is simulated by the pipeline's own stages
(:func:`regtrack.pipeline.stages.mesh_stage`, :func:`~regtrack.pipeline.stages.simulate_stage`),
so the mesh is built once and every simulation lands in (or is read from) the stage cache
that ``regtrack run`` and ``regtrack study`` share.  A view with a mammogram takes the
DICOM's geometry as ``regtrack run`` does (:func:`regtrack.pipeline.geometry.apply_geometry`:
the MLO angle; a design's ``target_D`` wins over the DICOM's thickness).  The displacement of a run is its
deformed positions minus the model's nodes (mm).

The study engine (:mod:`regtrack.study.engine`) is not used: its runners return one flat row
of registration metrics per view, not a displacement field, and its pipeline runner also
renders and registers every view.  The stage cache gives the same re-use.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack.errors import ConfigError, RegtrackError

log = logging.getLogger(__name__)

Say = Callable[[str], None]


@dataclass
class Simulations:
    """Displacement fields of one view at parameter points (failed points are left out)."""

    names: tuple[str, ...]
    params: np.ndarray  # (n, d)
    fields: np.ndarray  # (n, N, 3) mm
    seconds: list[float] = field(default_factory=list)
    failed: list[dict] = field(default_factory=list)


def simulate_points(case: Any, view: str, names: tuple[str, ...], points: np.ndarray, *,
                    cache_dir: str | Path, say: Say | None = None,
                    overrides: dict | None = None) -> Simulations:
    """Simulate ``view`` of ``case`` at each row of ``points``; a run that does not converge
    is recorded in ``failed`` and skipped."""
    from regtrack.case import resolve_configs
    from regtrack.pipeline import stages
    from regtrack.pipeline.geometry import apply_geometry
    from regtrack.pipeline.run import open_run
    from regtrack.study.params import apply_point

    say = say or log.info
    view = view.upper()
    base = dict(overrides or {})
    ctx = open_run(case, resolve_configs(case, base), cache_dir=cache_dir)
    mesh = stages.mesh_stage(ctx)
    keep, fields, secs, failed = [], [], [], []
    for i, row in enumerate(np.atleast_2d(points)):
        point = dict(zip(names, map(float, row)))
        text = ", ".join(f"{k} {v:.4g}" for k, v in point.items())
        say(f"simulation {i + 1}/{len(points)}: {text}")
        configs = resolve_configs(case, apply_point(base, point, views=(view,)))
        run_ctx = open_run(case, configs, cache_dir=cache_dir)
        if view in case.views:  # the DICOM's MLO angle (and projection), as `regtrack run`
            apply_geometry(run_ctx, mesh.model, (view,))
        t0 = time.perf_counter()
        try:
            sim = stages.simulate_stage(run_ctx, mesh, view)
        except RegtrackError as err:  # a diverged point is a hole in the design, not the end
            log.warning("simulation %d (%s) failed and is left out: %s", i + 1, text, err)
            failed.append({"params": point, "error": str(err)})
            continue
        secs.append(time.perf_counter() - t0)
        keep.append(row)
        fields.append(np.asarray(sim.positions, float) - mesh.model.points)
    n_nodes = mesh.model.n_nodes
    return Simulations(tuple(names), np.asarray(keep, float).reshape(-1, len(names)),
                       np.asarray(fields, float).reshape(-1, n_nodes, 3), secs, failed)


def build_surrogate(case: Any, view: str, *, box: Any, n_points: int, n_holdout: int = 4,
                    cache_dir: str | Path, seed: int = 0, regressor: str = "gp",
                    say: Say | None = None, overrides: dict | None = None):
    """Simulate a Latin-hypercube design of ``n_points`` (+ ``n_holdout`` validation points),
    fit the surrogate and validate it; returns ``(surrogate, report)``.

    Raises
    ------
    ConfigError
        Fewer than ``len(box.names) + 2`` training runs converged (too few for the trend
        and one residual).
    """
    from regtrack.surrogate.model import fit_surrogate
    from regtrack.surrogate.validate import held_out

    say = say or log.info
    d = len(box.names)
    train_pts = box.sample(n_points, seed=seed)
    test_pts = box.sample(n_holdout, seed=seed + 1) if n_holdout else np.zeros((0, d))
    train = simulate_points(case, view, box.names, train_pts, cache_dir=cache_dir, say=say,
                            overrides=overrides)
    if len(train.params) < d + 2:
        raise ConfigError(f"surrogate: only {len(train.params)} of {n_points} training "
                          f"simulations converged; need at least {d + 2} (raise --points or "
                          "narrow the parameter ranges)")
    t0 = time.perf_counter()
    sur = fit_surrogate(train.params, train.fields, names=box.names, lower=box.lower,
                        upper=box.upper, regressor=regressor, seed=seed)
    fit_s = time.perf_counter() - t0
    report: dict[str, Any] = {
        "case": getattr(case, "id", None), "view": view.upper(), "regressor": regressor,
        "parameters": {n: [lo, hi] for n, lo, hi in zip(box.names, box.lower, box.upper)},
        "n_train": len(train.params), "n_nodes": sur.n_nodes, "n_modes": sur.basis.n_modes,
        "explained": [float(x) for x in sur.basis.explained],
        "train_points": train.params.tolist(), "failed": train.failed,
        "simulation_s": train.seconds, "fit_s": fit_s}
    if n_holdout:
        test = simulate_points(case, view, box.names, test_pts, cache_dir=cache_dir, say=say,
                               overrides=overrides)
        report["failed"] += test.failed
        report["simulation_s"] += test.seconds
        if len(test.params):
            report["held_out"] = held_out(sur, test.params, test.fields)
    _, report["predict_s"] = sur.timed_predict(train.params[0])
    sur.meta = {"validation": report}
    return sur, report
