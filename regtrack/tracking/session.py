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
from regtrack.tracking.viewmap import ViewMap, viewmap_from_outcome
from regtrack.views import VIEWS

log = logging.getLogger(__name__)



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
        Stage cache (default :data:`~regtrack.pipeline.cache.DEFAULT_CACHE`, as ``regtrack run``).
    overrides : dict, optional
        Config overrides in the case.toml layout (as :func:`regtrack.pipeline.run.run_case`).
    simulate : bool
        Run missing mesh/simulation stages (default); False raises TrackingError.
    config : TrackingConfig, optional
        Default: ``overrides``' ``[tracking]`` section on the class defaults.
    progress : callable, optional
        Called with one line per stage.

    Raises
    ------
    CaseError
        An unknown view, or one the case has no mammogram for.
    TrackingError
        A case without mammograms, or (``simulate=False``) a case whose
        simulations are not cached.
    """
    from regtrack.case import load_case, resolve_configs
    from regtrack.pipeline.run import (concurrent_default, missing_stages, open_run, run_stages,
                                       select_views)

    case = load_case(case_dir)
    names = select_views(case, views)
    if not case.views:
        raise TrackingError(f"{case.toml_path}: no [views.CC] or [views.MLO] in the case; add "
                            "a mammogram to case.toml to track into it")
    configs = resolve_configs(case, overrides)
    ctx = open_run(case, configs, cache_dir=cache_dir, progress=progress)
    from regtrack.pipeline import stages
    from regtrack.pipeline.geometry import apply_geometry

    mesh = None
    if ctx.cache.has("mesh", stages.mesh_key(ctx)):
        # the DICOM's plate gap and angle enter the simulations' keys (as in `regtrack run`)
        mesh = stages.mesh_stage(ctx)
        apply_geometry(ctx, mesh.model, names)
    todo = missing_stages(ctx, names)
    if todo and not simulate:
        raise TrackingError(f"case {case.id} not simulated yet ({', '.join(todo)} not in the cache "
                            f"{ctx.cache.root}): run `regtrack run {case.root}` first, or drop "
                            "--no-simulate to simulate now")
    if todo:
        ctx.say(f"track: {', '.join(todo)} not in the cache {ctx.cache.root}; running them now "
                "(this takes minutes; later calls re-use them)")
    mesh, outcomes = run_stages(ctx, names, concurrent=concurrent_default(), mesh=mesh)
    session = TrackingSession(case, mesh.model, {}, config=config or configs.tracking,
                              stage_keys={"mesh": mesh.key}, simulated_now=todo)
    for out in outcomes:
        session.views[out.view] = viewmap_from_outcome(out, config=session.config)
        session.outcomes[out.view] = out
        session.stage_keys[f"simulate_{out.view}"] = out.sim_key
    return session
