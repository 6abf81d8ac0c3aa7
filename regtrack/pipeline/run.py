"""``regtrack run``: MRI case in, report out.

Stages (each cached by :mod:`regtrack.pipeline.cache` under a key of everything it reads)::

    mesh ──> simulate[view] ──> virtual[view] ─┐
                                real[view] ────┴─> align + metrics[view] ─> report

Re-running after changing only registration settings re-uses the mesh and the
simulations; changing a material parameter re-runs the simulations but not the mesh.
Nothing is written into the case folder.  Every output file is written atomically.
"""

from __future__ import annotations

import dataclasses
import logging
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack import __version__, _io
from regtrack._signals import check_interrupted
from regtrack.case.configs import Configs
from regtrack.errors import CaseError, ConfigError, RegtrackError
from regtrack.pipeline import stages, workers
from regtrack.pipeline.cache import DEFAULT_CACHE, StageCache, file_digest, fingerprint
from regtrack.privacy import (IDENTIFYING_KEYWORDS, Identifiers, identifiers_of_case_folder,
                              pseudonymous_id, scrub_logs)
from regtrack.views import VIEWS

log = logging.getLogger(__name__)

Progress = Callable[[str], None]
#: ``sim_progress(view, step, t, **info)`` after every converged increment of a simulation
#: (``info``: ``increment`` in the step, and whatever the solver reports, e.g. ``D``,
#: ``force_N``); ``step`` None when the view's simulation has finished
SimProgress = Callable[..., None]


@dataclass
class RunContext:
    """Everything a stage needs: the case, its resolved configs, the cache."""

    case: Any
    configs: Configs
    cache: StageCache
    timings: dict[str, float] = field(default_factory=dict)
    progress: Progress | None = None
    #: identifiers to keep out of outputs (empty with --keep-identifiers)
    ids: Identifiers = field(default_factory=Identifiers)
    sim_progress: SimProgress | None = None
    #: (stage, key) of the stages produced in this run (by this process or its workers)
    produced: set = field(default_factory=set)
    #: each real view's acquisition geometry and its sources (regtrack.pipeline.geometry)
    geometry: dict = field(default_factory=dict)

    @property
    def protocol_tables(self) -> dict[str, dict]:
        """Each view's ``[protocol.<VIEW>]`` table (``configs.protocol_tables``)."""
        return self.configs.protocol_tables

    def say(self, msg: str) -> None:
        check_interrupted()  # a Ctrl-C swallowed in a finaliser stops the run here
        msg = self.ids.scrub(msg, console=True)
        log.info(msg)
        if self.progress is not None:
            self.progress(msg)

    def clean(self, obj: Any) -> Any:
        """``obj`` with patient identifiers and the case folder's path scrubbed."""
        return self.ids.scrub_obj(obj) if self.ids else obj


def run_case(case_dir: str | Path, *, overrides: dict | None = None,
             views: tuple[str, ...] | list[str] | None = None, cache_dir: str | Path | None = None,
             out_dir: str | Path | None = None, progress: Progress | None = None,
             report: bool = True, keep_identifiers: bool = False,
             concurrent: bool | None = None, sim_progress: SimProgress | None = None
             ) -> list[dict]:
    """Run the whole pipeline on a case; return one flat metrics row per view.

    Parameters
    ----------
    case_dir : path
        Case folder (or its case.toml).
    overrides : dict, optional
        Sections overriding case.toml (same layout), e.g. from a study.
    views : sequence of {"CC", "MLO"}, optional
        Default: every view the case has.
    cache_dir : path, optional
        Stage cache (default :data:`~regtrack.pipeline.cache.DEFAULT_CACHE`).
    out_dir : path, optional
        Where metrics, figures and the PDF go; nothing is written there when None.
    progress : callable, optional
        Called with one line per stage.
    sim_progress : callable, optional
        Called inside each simulation after every converged increment (see
        :data:`SimProgress`), from this process or, for views simulated at the same time,
        from a thread relaying the worker processes' reports.
    report : bool
        Write figures, the PDF and the DICOM results (a TID 1500 SR and the PDF as
        Encapsulated PDF, :mod:`regtrack.report.dicom_sr`; ``out_dir`` required).
    keep_identifiers : bool
        Copy the DICOM patient identifiers into ``provenance.json`` and scrub nothing.
        By default (False) no identifier of the inputs (:mod:`regtrack.privacy`) reaches
        an output, a progress line or a log record, and a case id that contains one is
        replaced by a pseudonym.
    concurrent : bool, optional
        Simulate the views that are not cached at the same time, one process each
        (:func:`regtrack.pipeline.workers.simulate_concurrently`).  Default (None): when this
        process may use two or more cores and may start processes (not a daemon, such as
        a Dask worker).  Studies pass False: they already run cases side by side.
    """
    t_start = time.perf_counter()
    found = identifiers_of_case_folder(case_dir)
    ids = Identifiers() if keep_identifiers else found
    with scrub_logs(ids):  # the loader's messages name the case's files
        return _run_case(case_dir, found, ids, overrides=overrides, views=views,
                         cache_dir=cache_dir, out_dir=out_dir, progress=progress, report=report,
                         keep_identifiers=keep_identifiers, t_start=t_start,
                         sim_progress=sim_progress,
                         concurrent=concurrent_default() if concurrent is None else concurrent)


def concurrent_default() -> bool:
    """Simulate views at the same time: two or more usable cores and not a daemon process."""
    import multiprocessing

    from regtrack.mechanics.parallel import thread_count

    return thread_count(0) >= 2 and not multiprocessing.current_process().daemon


def _run_case(case_dir, found: Identifiers, ids: Identifiers, *, overrides, views, cache_dir,
              out_dir, progress, report, keep_identifiers, t_start, concurrent,
              sim_progress=None) -> list[dict]:
    from regtrack.case import load_case, resolve_configs

    case = load_case(case_dir)
    views = select_views(case, views)
    if not case.views:
        # no mammograms: simulate and project (virtual mammograms only), say so
        log.warning("%s: the case has no [views.*] (no real mammograms): running mesh, "
                    "simulation and virtual mammograms only; registration and metrics need "
                    "[views.CC]/[views.MLO] with a mammogram", case.toml_path)
        if progress is not None:
            progress("no real mammograms in this case: registration and metrics are skipped")
    if not keep_identifiers:
        case = dataclasses.replace(case, id=pseudonymous_id(case.id, found),
                                   title=found.redact(case.title, "[case] title"))
    ctx = open_run(case, resolve_configs(case, overrides), cache_dir=cache_dir,
                   progress=progress, ids=ids, sim_progress=sim_progress)
    mesh_out, results = run_stages(ctx, views, concurrent=concurrent)
    rows = [r.row for r in results]
    ctx.timings["total"] = time.perf_counter() - t_start
    if out_dir is not None:
        out = Path(out_dir)
        _remove_stale_parts(out)
        prov = ctx.clean(provenance(ctx, mesh_out, results))
        prov["privacy"] = ({"identifiers": "kept (--keep-identifiers)",
                            "patient": found.by_keyword} if keep_identifiers else
                           {"identifiers": "removed", "attributes_checked": len(IDENTIFYING_KEYWORDS)})
        rows = ctx.clean(rows)
        _io.write_json(out / "metrics.json", {"case_id": case.id, "mode": prov["mode"],
                                              "views": rows})
        if any(r.extra.get("lesions") for r in results):
            _io.write_json(out / "lesions.json", ctx.clean(lesions_doc(case.id, results)))
        _io.write_text(out / "metrics.csv", _csv(rows))
        _io.write_json(out / "provenance.json", prov)
        if report:  # figures, the PDF, and the DICOM SR + encapsulated PDF for the PACS
            pdf = stages.report_stage(ctx, mesh_out, results, out, prov)
            stages.dicom_stage(ctx, results, out, pdf, keep_identifiers=keep_identifiers)
    log.info("case %s done in %.1f s (cache: %d hits, %d misses)", case.id,
             ctx.timings["total"], ctx.cache.hits, ctx.cache.misses)
    return rows


def select_views(case: Any, views: tuple[str, ...] | list[str] | None = None) -> tuple[str, ...]:
    """The views to run, upper-cased: ``views``, or every view of the case (both when the
    case has no mammogram: the virtual-only run).

    Raises :class:`CaseError` for a name outside :data:`regtrack.views.VIEWS`, or a view
    the case has no ``[views.<V>]`` for (when it has any).
    """
    names = tuple(str(v).upper() for v in (views or tuple(case.views) or VIEWS))
    unknown = [v for v in names if v not in VIEWS]
    if unknown:
        raise CaseError(f"--views: unknown view {unknown[0]!r}; use "
                        f"{' and/or '.join(VIEWS)}")
    missing = [v for v in names if case.views and v not in case.views]
    if missing:
        raise CaseError(f"{case.toml_path}: view(s) {', '.join(missing)} requested but the "
                        f"case has {', '.join(case.views)}; add [views.{missing[0]}] or "
                        "choose --views from those")
    return names


def open_run(case: Any, configs: Configs, *, cache_dir: str | Path | None = None,
             progress: Progress | None = None, ids: Identifiers | None = None,
             sim_progress: SimProgress | None = None) -> RunContext:
    """The context every stage of a run of ``case`` reads: its ``configs``
    (:func:`regtrack.case.resolve_configs`) and the stage cache (``cache_dir``, default
    :data:`~regtrack.pipeline.cache.DEFAULT_CACHE`).

    The entry point of ``regtrack run`` (:func:`run_case`) and ``regtrack track``
    (:func:`regtrack.tracking.session.open_case`); ``ids`` are the identifiers to keep out
    of outputs (none by default).  A configuration no stage can run (``formulation =
    "p2"``: the mesh stage makes 4-node tetrahedra) is a :class:`ConfigError` here,
    before any stage.
    """
    if configs.mechanics.formulation == "p2":
        raise ConfigError("[mechanics] formulation = 'p2' needs a 10-node tetrahedral model, and "
                          "regtrack's mesh stage makes 4-node ones: use 'p1-anp' (the default) or "
                          "'p1' here ('p2' is for tet10 models in Python, "
                          "regtrack.mechanics.p2.model_to_p2)")
    cache = StageCache(Path(cache_dir) if cache_dir else DEFAULT_CACHE)
    return RunContext(case, configs, cache, progress=progress,
                      ids=ids if ids is not None else Identifiers(), sim_progress=sim_progress)


def missing_stages(ctx: RunContext, views: tuple[str, ...] | list[str]) -> list[str]:
    """Names of the expensive stages (``mesh``, ``simulate_<view>``) not in the cache yet."""
    mk = stages.mesh_key(ctx)
    out = [] if ctx.cache.has("mesh", mk) else ["mesh"]
    out += [f"simulate_{v}" for v in views
            if not ctx.cache.has("simulate", stages.simulate_key(ctx, mk, v))]
    return out


def run_stages(ctx: RunContext, views: tuple[str, ...], *, concurrent: bool,
               mesh: stages.MeshOutput | None = None
               ) -> tuple[stages.MeshOutput, list[stages.ViewOutcome]]:
    """Mesh, then per view simulate, virtual mammogram and (with a real mammogram) the
    alignment and metrics; the real mammograms are read first, so that a bad DICOM fails
    in seconds, before any stage is computed or cached.  ``concurrent``: simulate the
    uncached views at the same time (:func:`.workers.simulate_concurrently`); ``mesh``: the
    mesh stage's output when the caller has it already."""
    reals = {view: stages.real_stage(ctx, view) for view in views if view in ctx.case.views}
    mesh_out = mesh if mesh is not None else stages.mesh_stage(ctx)
    if ctx.case.views and not ctx.geometry:  # the DICOM's plate gap, MLO angle, projection
        from regtrack.pipeline.geometry import apply_geometry

        apply_geometry(ctx, mesh_out.model, views)
    failed = workers.simulate_concurrently(ctx, mesh_out, views) if concurrent else {}
    results = []
    for view in views:
        if view in failed:
            raise failed[view]
        sim = stages.simulate_stage(ctx, mesh_out, view)
        virtual = stages.virtual_stage(ctx, mesh_out, sim, view)
        if view in reals:
            results.append(stages.align_stage(ctx, mesh_out, sim, virtual, reals[view], view))
        else:
            results.append(stages.virtual_only(ctx, sim, virtual, view))
    return mesh_out, results


def _remove_stale_parts(out: Path) -> None:
    """Delete temporary files (``.<name>.*.part<ext>``, see :func:`regtrack._io.atomic_path`)
    left in ``out`` by a run that was killed while writing; they are never read."""
    if not out.is_dir():
        return
    stale = [p for p in out.rglob(".*.part*") if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    if stale:
        log.info("removed %d unfinished file(s) of an interrupted run from %s", len(stale), out)


def _csv(rows: list[dict]) -> str:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]

    def cell(v):
        if v is None or (isinstance(v, float) and not np.isfinite(v)):
            return ""
        return f"{v:.10g}" if isinstance(v, float) else str(v)
    return "\n".join([",".join(keys)] + [",".join(cell(r.get(k)) for k in keys) for r in rows]) + "\n"


def run_mode(results) -> str | None:
    """``"paper"`` (every view has a tumour outline), ``"tracking"`` (none has), ``"mixed"``,
    or None without real mammograms (simulation and virtual mammograms only)."""
    modes = {r.extra.get("mode") for r in results} - {None}
    if not modes:
        return None
    return modes.pop() if len(modes) == 1 else "mixed"


def lesions_doc(case_id: str, results) -> dict:
    """``lesions.json``: every MRI lesion predicted on every real mammogram."""
    return {
        "case_id": case_id, "mode": run_mode(results),
        "frames": {"mm": "real mammogram, canonical frame (chest wall left, x towards the "
                         "nipple, y down), mm", "px_rc": "(row, col) of the DICOM's own grid"},
        "method": "registration on the breast outline and nipple only (theta_p = theta_p,b); "
                  "sigma_mm: 1-sigma radius from the local registration residual, the angular "
                  "uncertainty times the distance from the nipple, the model's sensitivity "
                  "to D, c1 and nu, and how far the prediction moves when the registration "
                  "is repeated with the nipple moved along the run of the apex where it was "
                  "detected (regtrack.tracking.uncertainty); error_mm: distance to the "
                  "area centroid of the annotated outline paired with the lesion (paper "
                  "mode; regtrack.registration.geometry.pair_points)",
        "views": {r.view: {"mode": r.extra.get("mode"),
                           "lesions": [p.to_dict() for p in r.extra.get("lesions") or []]}
                  for r in results if r.extra.get("mode")},
    }


def provenance(ctx: RunContext, mesh_out, results) -> dict:
    """Configuration, versions, inputs and timings of a run (written into every output)."""
    import importlib.metadata as md

    from regtrack.pipeline.outputs import input_digests

    versions = {"regtrack": __version__, "python": platform.python_version()}
    for pkg in ("numpy", "scipy", "gmsh", "pydicom", "scikit-image", "opencv-python-headless",
                "shapely", "meshio", "pypardiso", "numba"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return {
        "case_id": ctx.case.id,
        "mode": run_mode(results),
        "view_modes": {r.view: {"mode": r.extra.get("mode"), "why": r.extra.get("mode_reason")}
                       for r in results if r.extra.get("mode")},
        "config": ctx.configs.to_tables(),
        "geometry": {v: g.to_dict() for v, g in ctx.geometry.items()},
        "protocol_overrides": ctx.configs.protocol_tables,
        "overrides": ctx.configs.overrides,
        "inputs": input_digests(ctx.case),
        "stage_keys": {"mesh": mesh_out.key, **{f"simulate_{r.view}": r.sim_key for r in results}},
        "cache": {"hits": ctx.cache.hits, "misses": ctx.cache.misses},
        "timings_s": ctx.timings,
        "versions": versions,
        "platform": platform.platform(),
    }


__all__ = ["run_case", "open_run", "run_stages", "select_views", "missing_stages",
           "RegtrackError", "fingerprint", "file_digest"]
