"""A case ready for tracking: the model, the simulated views and their alignments.

:func:`open_case` runs the stages of ``regtrack run`` up to the alignment through the
same stage cache (:mod:`regtrack.pipeline.cache`), so a case already run is tracked in
seconds: the mesh and the simulations are found in the cache and only the 2-D stages
(virtual mammogram, real mammogram, registration) are recomputed.  A case not simulated
yet is simulated first (with progress messages) unless ``simulate=False``, which raises
:class:`~regtrack.errors.TrackingError` instead.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from regtrack.errors import TrackingError
from regtrack.model.types import BreastModel
from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.locate import TetLocator
from regtrack.tracking.uncertainty import Residual
from regtrack.tracking.viewmap import InPlane, PixelFrame, ViewMap

log = logging.getLogger(__name__)

VIEWS = ("CC", "MLO")


@dataclass
class TrackingSession:
    """Model, view maps and pipeline outcomes of one case."""

    case: Any
    model: BreastModel
    views: dict[str, ViewMap]
    outcomes: dict[str, Any] = field(default_factory=dict)   # view -> pipeline ViewOutcome
    config: TrackingConfig = field(default_factory=TrackingConfig)
    stage_keys: dict[str, str] = field(default_factory=dict)
    simulated_now: list[str] = field(default_factory=list)
    _view_locators: dict = field(default_factory=dict, repr=False)

    @cached_property
    def locator(self) -> TetLocator:
        """Point location in the reference (prone MRI) mesh."""
        return TetLocator(self.model.points, self.model.tets)

    def view_locator(self, view: str) -> TetLocator:
        """Point location in the compressed mesh of ``view``."""
        v = self.view(view)
        if v.view not in self._view_locators:
            self._view_locators[v.view] = TetLocator(v.positions, self.model.tets)
        return self._view_locators[v.view]

    def view(self, name: str) -> ViewMap:
        """The view map of ``name`` (case-insensitive); TrackingError names the choices."""
        key = str(name).upper()
        if key not in VIEWS:
            raise TrackingError(f"unknown view {name!r}: use CC or MLO")
        if key not in self.views:
            raise TrackingError(f"{self.case.toml_path}: the case has no [views.{key}] "
                                f"(views: {', '.join(self.views) or 'none'}); add its mammogram "
                                "to case.toml to track into it")
        return self.views[key]


def viewmap_from_outcome(outcome, *, alignment=None) -> ViewMap:
    """The :class:`ViewMap` of a pipeline :class:`~regtrack.pipeline.stages.ViewOutcome`
    (simulated positions, virtual plate frame and source, alignment, real view).

    For the case report: ``track_tumour(model, {o.view: viewmap_from_outcome(o) for o in
    results})`` gives the tumour's predicted position in every real view.  ``alignment``
    replaces the outcome's (e.g. its breast-only registration, ``extra["breast_alignment"]``).
    """
    al = alignment if alignment is not None else outcome.alignment
    return ViewMap(outcome.view, outcome.sim.positions, outcome.virtual.frame,
                   InPlane.from_alignment(al), PixelFrame.from_view(outcome.real),
                   outcome.virtual.source, Residual.from_alignment(al), outcome.real)


def _simulate_key(ctx, mesh_key: str, view: str) -> str:
    """Key of the simulate stage (the pipeline's own :func:`simulate_key`)."""
    from regtrack.pipeline.stages import simulate_key

    return simulate_key(ctx, mesh_key, view)


def missing_stages(ctx, views) -> list[str]:
    """Names of the expensive stages (mesh, simulate_<view>) not in the cache yet."""
    from regtrack.pipeline import stages
    from regtrack.pipeline.cache import MARKER

    mk = stages.mesh_key(ctx)
    out = [] if (ctx.cache.folder("mesh", mk) / MARKER).is_file() else ["mesh"]
    for v in views:
        if not (ctx.cache.folder("simulate", _simulate_key(ctx, mk, v)) / MARKER).is_file():
            out.append(f"simulate_{v}")
    return out


def open_case(case_dir: str | Path, *, views: tuple[str, ...] | list[str] | None = None,
              cache_dir: str | Path | None = None, overrides: dict | None = None,
              simulate: bool = True, config: TrackingConfig | None = None,
              progress: Callable[[str], None] | None = None) -> TrackingSession:
    """Load a case, find (or run) its mesh and simulations, align every view.

    Parameters
    ----------
    case_dir : path
        Case folder or its case.toml.
    views : sequence of {"CC", "MLO"}, optional
        Default: every view of the case.
    cache_dir : path, optional
        Stage cache (default ``.regtrack-cache``, as ``regtrack run``).
    overrides : dict, optional
        Config overrides in the case.toml layout (as :func:`regtrack.pipeline.run.run_case`).
    simulate : bool
        Run missing mesh/simulation stages (default); False raises TrackingError.
    progress : callable, optional
        Called with one line per stage.

    Raises
    ------
    TrackingError
        Unknown view, a case without mammograms, or (``simulate=False``) a case whose
        simulations are not cached.
    """
    from regtrack.case import load_case
    from regtrack.pipeline import stages
    from regtrack.pipeline.cache import StageCache
    from regtrack.pipeline.run import RunContext, concurrent_default, effective_configs

    case = load_case(case_dir)
    names = tuple(str(v).upper() for v in (views or tuple(case.views)))
    bad = [v for v in names if v not in VIEWS]
    if bad:
        raise TrackingError(f"unknown view {bad[0]!r}: use CC or MLO")
    missing = [v for v in names if v not in case.views]
    if missing or not names:
        raise TrackingError(f"{case.toml_path}: no [views.{(missing or ['CC'])[0]}] in the case "
                            f"(views: {', '.join(case.views) or 'none'}); add the mammogram to "
                            "case.toml to track into it")
    configs, protocol_tables = effective_configs(case, overrides)
    cache = StageCache(Path(cache_dir) if cache_dir else Path(".regtrack-cache"))
    ctx = RunContext(case, configs, protocol_tables, cache, progress=progress)
    from regtrack.pipeline.cache import MARKER
    from regtrack.pipeline.geometry import resolve_geometry

    if (cache.folder("mesh", stages.mesh_key(ctx)) / MARKER).is_file():
        # the DICOM's plate gap and angle enter the simulations' keys (as in `regtrack run`)
        ctx.geometry = resolve_geometry(ctx, stages.mesh_stage(ctx).model, views=names)
    todo = missing_stages(ctx, names)
    if todo and not simulate:
        raise TrackingError(f"case {case.id} not simulated yet ({', '.join(todo)} not in the cache "
                            f"{cache.root}): run `regtrack run {case.root}` first, or drop "
                            "--no-simulate to simulate now")
    if todo:
        ctx.say(f"track: {', '.join(todo)} not in the cache {cache.root}; running them now "
                "(this takes minutes; later calls re-use them)")
    mesh = stages.mesh_stage(ctx)
    if not ctx.geometry:
        ctx.geometry = resolve_geometry(ctx, mesh.model, views=names)
    cfg = config or configs.get("tracking") or TrackingConfig()
    session = TrackingSession(case, mesh.model, {}, config=cfg, stage_keys={"mesh": mesh.key},
                              simulated_now=todo)
    failed = stages.simulate_concurrently(ctx, mesh, names) if concurrent_default() else {}
    for v in names:
        if v in failed:
            raise failed[v]
        sim = stages.simulate_stage(ctx, mesh, v)
        vm = stages.virtual_stage(ctx, mesh, sim, v)
        real = stages.real_stage(ctx, v)
        out = stages.align_stage(ctx, mesh, sim, vm, real, v)
        session.views[v] = viewmap_from_outcome(out)
        session.outcomes[v] = out
        session.stage_keys[f"simulate_{v}"] = sim.key
    return session
