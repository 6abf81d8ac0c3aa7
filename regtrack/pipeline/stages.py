"""The stages of ``regtrack run``, each a small function over :class:`RunContext`.

Expensive stages (mesh, simulate) are cached; the 2-D stages (virtual mammogram, real
mammogram, alignment, metrics) take seconds and are recomputed from the cached
simulation, so changing a registration setting never re-simulates.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack.config import to_table
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


def add_time(ctx, name: str, t0: float) -> None:
    """Add the seconds since ``t0`` to ``ctx.timings[name]`` (the run's stage timings)."""
    ctx.timings[name] = ctx.timings.get(name, 0.0) + time.perf_counter() - t0


# -- mesh ---------------------------------------------------------------------------------
def mesh_key(ctx) -> str:
    case = ctx.case
    mri = case.mri
    return fingerprint("mesh", file_digest(mri.labels), to_table(mri.scheme), mri.side,
                       mri.nipple_lps_mm, to_table(ctx.configs.model))


def mesh_stage(ctx) -> MeshOutput:
    """Build (or find) the patient model of the case."""
    from regtrack.model.io import load_model, save_model

    key = mesh_key(ctx)
    hit = ctx.cache.lookup("mesh", key)
    t0 = time.perf_counter()
    if hit is None:
        from regtrack.imaging.readers import read_label_map
        from regtrack.model.build import build_model
        from regtrack.model.pictures import save_pictures

        ctx.say("mesh: building the patient model from the label map")
        mri = ctx.case.mri
        labels = read_label_map(mri.labels)
        nipple = None if mri.nipple_lps_mm is None else np.asarray(mri.nipple_lps_mm, float)
        model = build_model(labels, scheme=mri.scheme, config=ctx.configs.model, side=mri.side,
                            nipple_lps=nipple, progress=lambda m: ctx.say(f"mesh: {m}"))
        model.meta = ctx.clean(model.meta)  # input paths may name the patient
        with ctx.cache.produce("mesh", key, info={"nodes": model.n_nodes, "tets": model.n_tets}) as d:
            save_model(model, d / "model.vtu")
            save_pictures(model, d / "model")  # a stem: model_sections.png, model_3d.png
        hit = ctx.cache.folder("mesh", key)
    else:
        ctx.say("mesh: found in the cache")
    model = load_model(hit / "model.vtu")
    add_time(ctx, "mesh", t0)
    return MeshOutput(key, hit, model)


# -- simulate -----------------------------------------------------------------------------
def simulate_key(ctx, mesh_key_: str, view: str) -> str:
    """Cache key of the ``view`` simulation: the mesh key, mechanics, contact and protocol."""
    return fingerprint("simulate", mesh_key_, view, to_table(ctx.configs.mechanics),
                       to_table(ctx.configs.contact), ctx.configs.protocols[view].to_dict())


def stopped_folder(ctx, key: str) -> Path:
    """Where a simulation that stopped keeps its balanced steps:
    ``<cache>/simulate/<key>.stopped/`` (never a cache hit: it has no completion marker)."""
    return ctx.cache.folder("simulate", key).with_name(f"{key}.stopped")


def simulate_stage(ctx, mesh: MeshOutput, view: str) -> SimOutput:
    """Simulate the mammography of ``view`` on the model (or find it in the cache)."""
    protocol = ctx.configs.protocols[view]
    mech, contact = ctx.configs.mechanics, ctx.configs.contact
    key = simulate_key(ctx, mesh.key, view)
    hit = ctx.cache.lookup("simulate", key)
    t0 = time.perf_counter()
    if hit is None:
        from regtrack.mechanics.run_view import simulate_view

        ctx.say(f"simulate {view}: {protocol.name} protocol ({len(protocol.steps)} steps)")
        with ctx.cache.produce("simulate", key, info={"view": view}) as d:
            # a stopped run's balanced steps outlive the temporary folder, which is removed
            simulate_view(ctx.case, mesh.model, view, out_dir=d, mechanics=mech, contact=contact,
                          protocol=protocol, progress=increment_hook(ctx, view),
                          partial_dir=stopped_folder(ctx, key))
            for f in d.iterdir():  # fixed names inside the cache folder
                suffix = "_steps.png" if f.name.endswith("_steps.png") else f.suffix
                f.rename(d / f"result{suffix}")
            _checked_result(ctx, d, mesh, view)  # a failed check never enters the cache
        hit = ctx.cache.folder("simulate", key)
        ctx.produced.add(("simulate", key))
        if ctx.sim_progress is not None:
            ctx.sim_progress(view, None, 1.0)
        ctx.say(f"simulate {view}: done ({time.perf_counter() - t0:.0f} s)")
    elif ("simulate", key) not in ctx.produced:  # not just simulated by a worker process
        ctx.say(f"simulate {view}: found in the cache")
    doc, positions = _checked_result(ctx, hit, mesh, view)
    angle = (doc.get("plate_frame") or {}).get("angle_deg")
    add_time(ctx, f"simulate_{view}", t0)
    return SimOutput(view, key, hit, doc["summary"], doc["steps"], positions, angle)


def increment_hook(ctx, view: str):
    """The solver's ``progress(step_name, t, **info)`` callback (called after every
    converged increment, and with ``working_to`` after every Newton iteration of the
    increment being solved) relayed to ``ctx.sim_progress(view, step, t, increment=k,
    **info)``, with ``k`` the increment's number in its step (counted here: it restarts
    when a step starts again from a smaller t, as an automatic retry does; the increment
    being solved is the next number).  None when nobody listens."""
    if ctx.sim_progress is None:
        return None
    state = {"step": None, "t": 0.0, "k": 0}

    def hook(step_name: str, t: float, *_: Any, **info: Any) -> None:
        t = float(t)
        if step_name != state["step"] or t < state["t"]:
            state.update(step=step_name, k=0)
        state["t"] = t
        if info.get("working_to") is None:
            state["k"] += 1
            ctx.sim_progress(view, step_name, t, **{"increment": state["k"], **info})
        else:
            ctx.sim_progress(view, step_name, t, **{"increment": state["k"] + 1, **info})
    return hook


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
                     max_penetration_mm=ctx.configs.contact.max_penetration_mm)
    return doc, positions


# -- 2-D stages ---------------------------------------------------------------------------
def virtual_stage(ctx, mesh: MeshOutput, sim: SimOutput, view: str):
    """Virtual mammogram of the compressed model (projection on the lower plate)."""
    from regtrack.virtual.project import default_frame, project_model

    t0 = time.perf_counter()
    ctx.say(f"virtual {view}: projecting the compressed model")
    frame = default_frame(sim.positions, view, mesh.model.frame.side, angle_deg=sim.angle_deg)
    geo = (getattr(ctx, "geometry", None) or {}).get(view)
    cfg = geo.virtual if geo is not None and geo.virtual is not None else ctx.configs.virtual
    vm = project_model(mesh.model, sim.positions, view=view, config=cfg,
                       frame=frame, source_name=f"virtual:{ctx.case.id}:{view}")
    add_time(ctx, f"virtual_{view}", t0)
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
    add_time(ctx, f"real_{view}", t0)
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
    from regtrack.metrics import compute_metrics
    from regtrack.registration import align
    from regtrack.tracking.lesions import predict_lesions
    from regtrack.tracking.viewmap import breast_alignment

    t0 = time.perf_counter()
    cfg = ctx.configs.registration
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
        "skin_overlap_mm": sim.summary.get("skin_overlap_mm"),
        "newton_iterations": sim.summary.get("iterations"),
    }
    if m.tumour_distance is not None:
        row.update({"tumour_dist_mean_mm": md["tumour_distance"]["mean"],
                    "tumour_hausdorff_mm": md["tumour_distance"]["hausdorff"]})
    al_b = breast_alignment(al, real, vm.view)
    sigma_D = _degree_sigma(ctx, sim, view)
    lesions = predict_lesions(mesh.model, view=view, positions=sim.positions, virtual=vm,
                              real=real, alignment=al_b, D=D, sigma_D=sigma_D,
                              config=ctx.configs.tracking)
    if lesions:
        # the row's lesion: in paper mode the first one paired with an outline
        first = next((p for p in lesions if p.error_mm is not None), lesions[0])
        row.update({"n_lesions": len(lesions), "lesion_x_mm": float(first.centroid_mm[0]),
                    "lesion_y_mm": float(first.centroid_mm[1]),
                    "lesion_row_px": None if first.centroid_px is None else float(first.centroid_px[0]),
                    "lesion_col_px": None if first.centroid_px is None else float(first.centroid_px[1]),
                    "lesion_sigma_mm": first.sigma_mm, "lesion_error_mm": first.error_mm})
    row.update(_geometry_columns(ctx, sim, view))
    from regtrack.pipeline.guards import check_metrics_row

    check_metrics_row(f"register {view}", row)
    add_time(ctx, f"register_{view}", t0)
    return ViewOutcome(view, sim.key, row, real, vm, al, m, sim,
                       extra={"mode": mode, "mode_reason": why, "lesions": lesions,
                              "breast_alignment": al_b, "sigma_D": sigma_D})


def _degree_sigma(ctx, sim: SimOutput, view: str) -> float:
    """1-sigma uncertainty of D: from the DICOM thickness when it set the gap, else the
    nominal ``[tracking] degree_sigma`` (:mod:`regtrack.tracking.uncertainty`)."""
    from regtrack.tracking.config import TrackingConfig

    cfg = ctx.configs.tracking or TrackingConfig()
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
           "skin_overlap_mm": sim.summary.get("skin_overlap_mm"),
           "newton_iterations": sim.summary.get("iterations")}
    return ViewOutcome(view, sim.key, row, None, vm, None, None, sim)


# -- outputs ------------------------------------------------------------------------------
def report_stage(ctx, mesh: MeshOutput, results: list[ViewOutcome], out: Path, prov: dict) -> Path:
    """Per-view JSON and figures, the 3-D files, the tracking and the PDF report
    (:func:`regtrack.pipeline.outputs.write_report`)."""
    from regtrack.pipeline.outputs import write_report

    return write_report(ctx, mesh, results, out, prov)


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
                                keep_identifiers=keep_identifiers, mri_series=ctx.case.mri.series)
    add_time(ctx, "dicom", t0)
    return paths

