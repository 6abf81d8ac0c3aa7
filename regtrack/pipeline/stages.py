"""The stages of ``regtrack run``, each a small function over :class:`RunContext`.

Expensive stages (mesh, simulate) are cached; the 2-D stages (virtual mammogram, real
mammogram, alignment, metrics) take seconds and are recomputed from the cached
simulation, so changing a registration setting never re-simulates.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack import _io
from regtrack.config import to_table
from regtrack.errors import RegtrackError
from regtrack.pipeline.cache import file_digest, fingerprint

log = logging.getLogger(__name__)


@dataclass
class MeshOutput:
    key: str
    folder: Path
    model: Any  # BreastModel

    @property
    def vtu(self) -> Path:
        return self.folder / "model.vtu"

    @property
    def pictures(self) -> list[Path]:
        return sorted(self.folder.glob("*.png"))


@dataclass
class SimOutput:
    view: str
    key: str
    folder: Path
    summary: dict
    steps: list[dict]
    positions: np.ndarray  # deformed node positions (mm, model frame)
    angle_deg: float | None

    @property
    def pictures(self) -> list[Path]:
        return sorted(self.folder.glob("*.png"))


@dataclass
class ViewOutcome:
    view: str
    sim_key: str
    row: dict
    real: Any
    virtual: Any  # VirtualMammogram
    alignment: Any
    metrics: Any
    sim: SimOutput
    extra: dict = field(default_factory=dict)


def _timed(ctx, name: str, t0: float) -> None:
    ctx.timings[name] = ctx.timings.get(name, 0.0) + time.perf_counter() - t0


# -- mesh ---------------------------------------------------------------------------------
def mesh_key(ctx) -> str:
    case = ctx.case
    mri = case.mri
    return fingerprint("mesh", file_digest(mri.labels), to_table(mri.scheme), mri.side,
                       mri.nipple_lps_mm, to_table(ctx.configs["model"]))


def mesh_stage(ctx) -> MeshOutput:
    """Build (or find) the patient model of the case."""
    from regtrack.model.io import load_model, save_model

    key = mesh_key(ctx)
    hit = ctx.cache.lookup("mesh", key)
    t0 = time.perf_counter()
    if hit is None:
        from regtrack.imaging.readers import read_label_map
        from regtrack.model.build import build_model

        ctx.say("mesh: building the patient model from the label map")
        mri = ctx.case.mri
        labels = read_label_map(mri.labels)
        nipple = None if mri.nipple_lps_mm is None else np.asarray(mri.nipple_lps_mm, float)
        model = build_model(labels, scheme=mri.scheme, config=ctx.configs["model"], side=mri.side,
                            nipple_lps=nipple, progress=lambda m: ctx.say(f"mesh: {m}"))
        model.meta = ctx.clean(model.meta)  # input paths may name the patient
        with ctx.cache.produce("mesh", key, info={"nodes": model.n_nodes, "tets": model.n_tets}) as d:
            save_model(model, d / "model.vtu")
            _model_pictures(model, d)
        hit = ctx.cache.folder("mesh", key)
    else:
        ctx.say("mesh: found in the cache")
    model = load_model(hit / "model.vtu")
    _timed(ctx, "mesh", t0)
    return MeshOutput(key, hit, model)


def _model_pictures(model, folder: Path) -> None:
    try:
        from regtrack.model import pictures
    except ImportError:  # pictures module optional
        return
    pictures.save_pictures(model, folder / "model")  # a stem: model_sections.png, model_3d.png


# -- simulate -----------------------------------------------------------------------------
def _protocol(ctx, view: str):
    from regtrack.mechanics.protocol import protocol_for_view

    return protocol_for_view(view, ctx.protocol_tables.get(view) or None,
                             where=str(ctx.case.toml_path), base_dir=ctx.case.root)


def simulate_key(ctx, mesh_key_: str, view: str) -> str:
    """Cache key of the ``view`` simulation: the mesh key, mechanics, contact and protocol."""
    return fingerprint("simulate", mesh_key_, view, to_table(ctx.configs["mechanics"]),
                       to_table(ctx.configs["contact"]), _protocol(ctx, view).to_dict())


def simulate_stage(ctx, mesh: MeshOutput, view: str) -> SimOutput:
    """Simulate the mammography of ``view`` on the model (or find it in the cache)."""
    protocol = _protocol(ctx, view)
    mech, contact = ctx.configs["mechanics"], ctx.configs["contact"]
    key = simulate_key(ctx, mesh.key, view)
    hit = ctx.cache.lookup("simulate", key)
    t0 = time.perf_counter()
    if hit is None:
        from regtrack.mechanics.run_view import simulate_view

        ctx.say(f"simulate {view}: {protocol.name} protocol ({len(protocol.steps)} steps)")
        with ctx.cache.produce("simulate", key, info={"view": view}) as d:
            simulate_view(ctx.case, mesh.model, view, out_dir=d, mechanics=mech, contact=contact,
                          protocol=protocol, progress=None)
            for f in d.iterdir():  # fixed names inside the cache folder
                suffix = "_steps.png" if f.name.endswith("_steps.png") else f.suffix
                f.rename(d / f"result{suffix}")
            _checked_result(ctx, d, mesh, view)  # a failed check never enters the cache
        hit = ctx.cache.folder("simulate", key)
    else:
        ctx.say(f"simulate {view}: found in the cache")
    doc, positions = _checked_result(ctx, hit, mesh, view)
    angle = (doc.get("plate_frame") or {}).get("angle_deg")
    _timed(ctx, f"simulate_{view}", t0)
    return SimOutput(view, key, hit, doc["summary"], doc["steps"], positions, angle)


def simulate_concurrently(ctx, mesh: MeshOutput, views, *, worker=None) -> dict[str, Exception]:
    """Simulate the ``views`` that are not in the cache at the same time, one process each
    (they are independent), so that :func:`simulate_stage` then finds every one there.

    Returns the error of each view whose simulation failed; the caller raises it when it
    reaches that view, and the other views' results are in the cache by then (nothing is
    lost).  A worker that dies or cannot send its error back leaves its view to be
    simulated again in this process (logged).  Does nothing when fewer than two views
    need simulating.  ``worker(ctx, mesh, view)`` (tests): a picklable function run in
    each process instead of :func:`_simulate_worker`; it returns seconds.

    Why: the Newton solver of one simulation keeps the two cores of the benchmark machine
    only partly busy (its GMRES solves on a stored factorisation are single-threaded and
    memory-bound, 36 % of the CC compression).  Measured on the 9,496-node benchmark
    hemisphere (``pipelines/bench_protocols.py`` with and without ``--concurrent``, back
    to back, session 34, 2 cores): CC + MLO one after the other 180.2 s, at the same time
    140.0 s (another pair: 146.9 and 128.6 s), the same Newton paths and forces (PARDISO
    in strict CNR mode, :mod:`regtrack.mechanics.linsolve`).
    """
    import concurrent.futures as cf
    import dataclasses
    import multiprocessing

    todo = [v for v in views
            if ctx.cache.lookup("simulate", simulate_key(ctx, mesh.key, v)) is None]
    if len(todo) < 2:
        return {}
    t0 = time.perf_counter()
    ctx.say(f"simulate {' and '.join(todo)} at the same time ({len(todo)} processes)")
    lite = dataclasses.replace(ctx, progress=None, timings={})
    failed: dict[str, Exception] = {}
    with cf.ProcessPoolExecutor(max_workers=len(todo),
                                mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(worker or _simulate_worker, lite, mesh, v): v for v in todo}
        for fut in cf.as_completed(futures):
            view = futures[fut]
            try:
                seconds = fut.result()
                ctx.say(f"simulate {view}: done ({seconds:.0f} s)")
            except RegtrackError as exc:
                failed[view] = exc
                ctx.say(f"simulate {view}: failed")
            except Exception as exc:  # a dead worker, an error that did not pickle
                log.warning("simulate %s: the worker process failed (%s: %s); simulating it "
                            "again in this process", view, type(exc).__name__, exc)
    _timed(ctx, "simulate_concurrent", t0)
    return failed


def _simulate_worker(ctx, mesh: MeshOutput, view: str) -> float:
    """One view's :func:`simulate_stage` in a worker process of
    :func:`simulate_concurrently`; warnings go to stderr, scrubbed like the caller's."""
    from regtrack.privacy import scrub_logs

    logging.basicConfig(level=logging.WARNING,
                        format=f"[{view}] %(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    with scrub_logs(ctx.ids):
        simulate_stage(ctx, mesh, view)
    return time.perf_counter() - t0


def _checked_result(ctx, folder: Path, mesh: MeshOutput, view: str) -> tuple[dict, np.ndarray]:
    """Result JSON and deformed positions of a simulate folder, after the guard rails."""
    from regtrack.pipeline.guards import check_simulation
    from regtrack.virtual.io import read_result_positions

    from regtrack.errors import InputFileError, ResultCheckError

    doc = json.loads((folder / "result.json").read_text())
    try:
        positions = read_result_positions(folder / "result.vtu", mesh.model)
    except InputFileError as err:
        raise ResultCheckError(f"simulate {view}: {err}") from err
    check_simulation(f"simulate {view}", doc, positions, mesh.model,
                     max_penetration_mm=ctx.configs["contact"].max_penetration_mm)
    return doc, positions


# -- 2-D stages ---------------------------------------------------------------------------
def virtual_stage(ctx, mesh: MeshOutput, sim: SimOutput, view: str):
    """Virtual mammogram of the compressed model (projection on the lower plate)."""
    from regtrack.virtual.project import default_frame, project_model

    t0 = time.perf_counter()
    ctx.say(f"virtual {view}: projecting the compressed model")
    frame = default_frame(sim.positions, view, mesh.model.frame.side, angle_deg=sim.angle_deg)
    geo = (getattr(ctx, "geometry", None) or {}).get(view)
    cfg = geo.virtual if geo is not None and geo.virtual is not None else ctx.configs.get("virtual")
    vm = project_model(mesh.model, sim.positions, view=view, config=cfg,
                       frame=frame, source_name=f"virtual:{ctx.case.id}:{view}")
    _timed(ctx, f"virtual_{view}", t0)
    return vm


def real_stage(ctx, view: str):
    """Read the real mammogram of ``view`` and extract contours and nipple."""
    from regtrack.case.annotations import read_tumour_mask, read_tumour_polygons
    from regtrack.imaging.mammogram import extract_view, read_mammogram

    t0 = time.perf_counter()
    vi = ctx.case.views[view]
    ctx.say(f"real {view}: reading {vi.mammogram.name}")
    img = read_mammogram(vi.mammogram, pixel_spacing_mm=vi.pixel_spacing_mm, view=view,
                         laterality=ctx.case.mri.side)
    polys = read_tumour_polygons(vi.tumour_polygon) if vi.tumour_polygon else None
    mask = read_tumour_mask(vi.tumour_mask) if vi.tumour_mask else None
    real = extract_view(img, tumour_polygon_px=polys, tumour_mask=mask, nipple_px=vi.nipple_px)
    if ctx.ids:  # file paths and notes may carry identifiers: never into an output
        real.source, real.meta = ctx.ids.scrub(real.source), ctx.ids.scrub_obj(real.meta)
    _timed(ctx, f"real_{view}", t0)
    return real


def view_mode(real, virtual, cfg) -> tuple[str, str | None]:
    """``("paper", None)`` when the real view has a tumour outline (and the model a tumour)
    and ``[registration] use_tumour`` is on: the paper's method, theta_p = (theta_p,b +
    theta_p,t) / 2.  Otherwise ``("tracking", why)``: the registration uses the breast
    outline and nipple only (theta_p = theta_p,b)."""
    if not cfg.use_tumour:
        return "tracking", "[registration] use_tumour = false"
    if not real.tumour_contours:
        return "tracking", "no tumour outline on the mammogram"
    if not virtual.tumour_contours:
        return "tracking", "the model's tumour has no projected outline"
    return "paper", None


def align_stage(ctx, mesh: MeshOutput, sim: SimOutput, vm, real, view: str) -> ViewOutcome:
    """Nipple superposition + golden-section rotation, the paper's metrics, and the MRI
    lesion(s) predicted on the mammogram.

    Paper mode (a tumour outline on the mammogram): the paper's registration and metrics,
    and the prediction's error against the outline.  Tracking mode (no outline): the
    registration on the breast outline and nipple only; the tumour metrics are absent
    (None) and the prediction is the result.  The prediction always comes from the
    breast-only registration (:mod:`regtrack.tracking.lesions`).
    """
    import dataclasses

    from regtrack.metrics import compute_metrics
    from regtrack.registration import align
    from regtrack.tracking.lesions import breast_alignment, predict_lesions

    t0 = time.perf_counter()
    cfg = ctx.configs.get("registration")
    mode, why = view_mode(real, vm.view, cfg)
    if mode == "tracking" and cfg.use_tumour:
        cfg = dataclasses.replace(cfg, use_tumour=False)
    ctx.say(f"register {view} ({mode} mode"
            f"{'' if why is None else ': ' + why}): golden-section search of the in-plane "
            "rotation")
    al = align(real, vm.view, config=cfg)
    D = sim.summary.get("D")
    m = compute_metrics(al, real, vm.view, D=D)
    md = m.to_dict()

    def num(x):
        return None if x is None or (isinstance(x, float) and not np.isfinite(x)) else x
    row = {
        "case_id": ctx.case.id, "view": view, "mode": mode,
        "BS_Av": m.bs_av, "TS_Av": num(m.ts_av),
        "theta_p_b": m.theta_p_b, "theta_p_t": num(m.theta_p_t), "theta_p": m.theta_p,
        "D": D, "d_T": num(m.d_T), "d_B": m.d_B,
        "force_N": sim.summary.get("upper_force_N"),
        "dice_breast": m.dice_breast, "dice_tumour": num(m.dice_tumour),
        "breast_dist_mean_mm": md["breast_distance"]["mean"],
        "breast_dist_p95_mm": md["breast_distance"]["p95"],
        "breast_hausdorff_mm": md["breast_distance"]["hausdorff"],
        "max_penetration_mm": sim.summary.get("max_penetration_mm"),
        "behind_chest_wall_mm": sim.summary.get("behind_chest_wall_mm"),
        "newton_iterations": sim.summary.get("iterations"),
    }
    if m.tumour_distance is not None:
        row.update({"tumour_dist_mean_mm": md["tumour_distance"]["mean"],
                    "tumour_hausdorff_mm": md["tumour_distance"]["hausdorff"]})
    al_b = breast_alignment(al, real, vm.view)
    lesions = predict_lesions(mesh.model, view=view, positions=sim.positions, virtual=vm,
                              real=real, alignment=al_b, D=D,
                              sigma_D=_degree_sigma(ctx, sim, view),
                              config=ctx.configs.get("tracking"))
    if lesions:
        first = lesions[0]
        row.update({"n_lesions": len(lesions), "lesion_x_mm": float(first.centroid_mm[0]),
                    "lesion_y_mm": float(first.centroid_mm[1]),
                    "lesion_row_px": None if first.centroid_px is None else float(first.centroid_px[0]),
                    "lesion_col_px": None if first.centroid_px is None else float(first.centroid_px[1]),
                    "lesion_sigma_mm": first.sigma_mm, "lesion_error_mm": first.error_mm})
    row.update(_geometry_columns(ctx, sim, view))
    from regtrack.pipeline.guards import check_metrics_row

    check_metrics_row(f"register {view}", row)
    _timed(ctx, f"register_{view}", t0)
    return ViewOutcome(view, sim.key, row, real, vm, al, m, sim,
                       extra={"mode": mode, "mode_reason": why, "lesions": lesions,
                              "breast_alignment": al_b})


def _degree_sigma(ctx, sim: SimOutput, view: str) -> float:
    """1-sigma uncertainty of D: from the DICOM thickness when it set the gap, else the
    nominal ``[tracking] degree_sigma`` (:mod:`regtrack.tracking.lesions`)."""
    from regtrack.tracking.config import TrackingConfig

    cfg = ctx.configs.get("tracking") or TrackingConfig()
    geo = (getattr(ctx, "geometry", None) or {}).get(view)
    T0 = sim.summary.get("T0_mm")
    if geo is not None and geo.gap_source == "dicom" and T0:
        return cfg.thickness_sigma_mm / float(T0)
    return cfg.degree_sigma


def _geometry_columns(ctx, sim: SimOutput, view: str) -> dict:
    """Plate gap and force of the simulation beside the DICOM's thickness and force."""
    geo = (getattr(ctx, "geometry", None) or {}).get(view)
    out = {"plate_gap_mm": sim.summary.get("plate_gap_mm")}
    if geo is not None:
        out.update(geo.row())
    return out


def virtual_only(ctx, sim: SimOutput, vm, view: str) -> ViewOutcome:
    """Outcome of a view without a real mammogram: simulation figures only."""
    row = {"case_id": ctx.case.id, "view": view, "D": sim.summary.get("D"),
           "force_N": sim.summary.get("upper_force_N"),
           "max_penetration_mm": sim.summary.get("max_penetration_mm"),
           "behind_chest_wall_mm": sim.summary.get("behind_chest_wall_mm"),
           "newton_iterations": sim.summary.get("iterations")}
    return ViewOutcome(view, sim.key, row, None, vm, None, None, sim)


# -- outputs ------------------------------------------------------------------------------
def report_stage(ctx, mesh: MeshOutput, results: list[ViewOutcome], out: Path, prov: dict) -> Path:
    """Per-view JSON and figures, then the PDF report."""
    from regtrack.report import figures as F
    from regtrack.report.pdf import CaseReport, ViewReport, write_pdf

    t0 = time.perf_counter()
    ctx.say("report: figures and PDF")
    views = []
    for r in results:
        vdir = out / r.view.lower()
        _io.write_json(vdir / "virtual.json", ctx.clean(r.virtual.view.to_dict()))
        _io.write_json(vdir / "simulation.json", ctx.clean({"summary": r.sim.summary,
                                                            "steps": r.sim.steps}))
        if r.real is not None:
            _io.write_json(vdir / "real.json", ctx.clean(r.real.to_dict()))
            _io.write_json(vdir / "alignment.json", ctx.clean(r.alignment.to_dict()))
            F.save_figure(F.overlay_figure(r.real, r.virtual.view, r.alignment), vdir / "overlay.png")
            F.save_figure(F.images_figure(r.real, r.virtual.view), vdir / "images.png")
        else:
            F.save_figure(F.virtual_figure(r.virtual.view), vdir / "virtual.png")
        for p in r.sim.pictures:
            _io.write_bytes(vdir / f"compression{p.suffix}", p.read_bytes())
        steps = [{"step": s.get("name"), "D": s.get("D"), "force_N": (s.get("contact") or {})
                  .get("upper", {}).get("normal_force_N"), "max_penetration_mm":
                  s.get("max_penetration_mm"), "behind_wall_mm": s.get("behind_chest_wall_mm"),
                  "increments": (s.get("solver") or {}).get("increments"),
                  "iterations": (s.get("solver") or {}).get("iterations"),
                  "seconds": (s.get("solver") or {}).get("seconds")} for s in r.sim.steps]
        views.append(ViewReport(r.view, r.row, r.real, r.virtual.view, r.alignment, steps,
                                [vdir / "compression.png"]))
    model = mesh.model
    ms = {"nodes": model.n_nodes, "tetrahedra": model.n_tets,
          "tumours": int(model.tumour_id.max(initial=0)), "skin triangles": len(model.skin),
          "fixed (chest-wall) nodes": int(model.fixed.sum()), "side": model.frame.side}
    for k in ("quality", "checks"):
        if isinstance(model.meta.get(k), dict):
            ms.update({f"{k}.{a}": b for a, b in list(model.meta[k].items())[:8]
                       if not isinstance(b, (dict, list))})
    pics = []
    for p in mesh.pictures:
        pics.append(_io.write_bytes(out / "model" / p.name, p.read_bytes()))
    tracking = _tracking_section(mesh, results, out) if all(r.real is not None for r in results) else None
    rep = CaseReport(ctx.case.id, ctx.case.title, views, ms, pics, prov["config"], prov,
                     extra_pages=[tracking] if tracking else [],
                     notes=report_notes(results, prov))
    path = write_pdf(rep, out / "report.pdf")
    _timed(ctx, "report", t0)
    return path


def dicom_stage(ctx, results: list[ViewOutcome], out: Path, pdf: Path | None, *,
                keep_identifiers: bool) -> list[Path]:
    """The DICOM SR (TID 1500) of the lesion predictions and metrics, and the PDF report as
    Encapsulated PDF, per study (:mod:`regtrack.report.dicom_sr`); under ``out/dicom``."""
    import importlib.util

    from regtrack.report.dicom_sr import write_dicom_results

    if not any(r.real is not None for r in results):
        return []
    if importlib.util.find_spec("highdicom") is None:
        log.warning("DICOM SR and encapsulated PDF not written: highdicom, a dependency of "
                    "regtrack, is not installed (pip install highdicom)")
        return []
    t0 = time.perf_counter()
    ctx.say("report: DICOM SR and encapsulated PDF")
    mammos = {v: vi.mammogram for v, vi in ctx.case.views.items()}
    paths = write_dicom_results(out, results, mammos, case_id=ctx.case.id, pdf_path=pdf,
                                keep_identifiers=keep_identifiers)
    _timed(ctx, "dicom", t0)
    return paths


def report_notes(results: list[ViewOutcome], prov: dict) -> list[str]:
    """The lines under the report's metrics table: the mode, each lesion prediction (mm of
    the real canonical frame, DICOM pixels), and the source of each geometry value."""
    mode = prov.get("mode")
    lines = []
    if mode is not None:
        what = {"paper": "paper (tumour outlines given: registration on breast and tumour, "
                         "theta_p = (theta_p,b + theta_p,t)/2; lesion predicted from the breast "
                         "registration alone, its error against the outline shown)",
                "tracking": "tracking (no tumour outline: registration on the breast outline "
                            "and nipple, theta_p = theta_p,b; the MRI lesion predicted)",
                "mixed": "mixed (paper mode where a view has a tumour outline, tracking "
                         "mode where it has none)"}[mode]
        lines.append(f"Mode: {what}")
    for r in results:
        for p in r.extra.get("lesions") or []:
            px = ("" if p.centroid_px is None
                  else f" = px (row {p.centroid_px[0]:.0f}, col {p.centroid_px[1]:.0f})")
            err = "" if p.error_mm is None else f"; error vs outline {p.error_mm:.1f} mm"
            t = p.terms_mm
            lines.append(f"{r.view} lesion {p.lesion}: ({p.centroid_mm[0]:.1f}, "
                         f"{p.centroid_mm[1]:.1f}) mm{px} ± {p.sigma_mm:.1f} mm (1σ: residual "
                         f"{t['registration_residual']:.1f}, rotation {t['rotation']:.1f}, model "
                         f"{t['model']:.1f}){err}")
    for view, geo in (prov.get("geometry") or {}).items():
        for key, item in geo.items():
            if isinstance(item, dict) and "source" in item:
                val = item.get("value")
                lines.append(f"{view} {key}: {val if val is not None else '–'}"
                             f"{' ' + item['unit'] if item.get('unit') and val is not None else ''}"
                             f" ({item['source']})")
    return lines


def _tracking_section(mesh: MeshOutput, results: list[ViewOutcome], out: Path):
    """Where the MRI tumour lands in each real mammogram (``tracking.json`` + a PDF page)."""
    from regtrack.tracking.figures import draw_tracking_page, report_section
    from regtrack.tracking.session import viewmap_from_outcome
    from regtrack.tracking.mri_to_view import track_tumour
    from regtrack.tracking.track import TrackResult

    if int(mesh.model.tumour_id.max(initial=0)) < 1:
        return None
    # the breast-only registration of the lesion prediction (lesions.json, the summary page)
    vms = {r.view: viewmap_from_outcome(r, alignment=r.extra.get("breast_alignment"))
           for r in results}
    res = TrackResult(results[0].row["case_id"], views={v: {} for v in vms},
                      mri=track_tumour(mesh.model, vms))
    for r in results:  # one lesion: the page shows the prediction's full 1-sigma radius
        lesions = r.extra.get("lesions") or []
        if len(lesions) == 1 and r.view in res.mri.views:
            res.mri.views[r.view].sigma_mm = lesions[0].sigma_mm
    _io.write_json(out / "tracking.json", report_section(res))
    reals = {r.view: r.real for r in results}
    return lambda fig: draw_tracking_page(fig, res, reals)
