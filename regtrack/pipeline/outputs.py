"""The outputs of ``regtrack run`` beside the metrics: per-view JSON and figures, the 3-D
files (:mod:`regtrack.report.export3d`), the lesion tracking and the PDF report
(:mod:`regtrack.report.pdf`).

Everything written here passes through ``ctx.clean`` (no patient identifier, no path of
the case folder) and is written atomically.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from regtrack import _io
from regtrack.case.configs import CONFIG_FIELDS
from regtrack.pipeline.cache import file_digest


def input_digests(case: Any) -> dict[str, str]:
    """SHA-256 of every input file of a case, keyed by its path inside the case folder."""
    root = Path(case.root)
    files: list[Path | None] = [case.mri.labels, getattr(case.mri, "series", None)]
    for v in case.views.values():
        files += [v.mammogram, v.tumour_polygon, v.tumour_mask]
    out: dict[str, str] = {}
    for f in files:
        if f is None or not Path(f).exists():
            continue
        p = Path(f)
        try:
            name = str(p.resolve().relative_to(root.resolve()))
        except ValueError:
            name = p.name
        out[name + ("/" if p.is_dir() else "")] = file_digest(p)
    return out


def step_states(sim) -> list[tuple[str, np.ndarray]]:
    """``(step name, displacement (N, 3) mm, model frame)`` after each protocol step, read
    from the simulation's ``result.vtu`` (point data ``displacement_<k>_<step>``)."""
    import meshio

    data = meshio.read(sim.folder / "result.vtu").point_data
    keyed = []
    for key, u in data.items():
        m = re.fullmatch(r"displacement_(\d+)_(.*)", key)
        if m:
            keyed.append((int(m.group(1)), np.asarray(u, float)))
    keyed.sort(key=lambda ku: ku[0])
    names = [s.get("name", f"step {k}") for k, s in enumerate(sim.steps, start=1)]
    return [(names[k - 1] if k - 1 < len(names) else f"step {k}", u) for k, u in keyed]


def _steps_rows(steps: list[dict]) -> list[dict]:
    out = []
    for s in steps:
        solver = s.get("solver") or {}
        out.append({"step": s.get("name"), "D": s.get("D"),
                    "force_N": ((s.get("contact") or {}).get("upper") or {}).get("normal_force_N"),
                    "max_penetration_mm": s.get("max_penetration_mm"),
                    "behind_wall_mm": s.get("behind_chest_wall_mm"),
                    "skin_overlap_mm": s.get("skin_overlap_mm"),
                    "increments": solver.get("increments"), "iterations": solver.get("iterations"),
                    "seconds": solver.get("t_total", solver.get("seconds"))})
    return out


def model_rows(model) -> list[list[str]]:
    """The appendix's model table: size, volumes and mesh quality."""
    from regtrack.report.export3d import tumour_centroid
    from regtrack.report.fmt import num

    q = model.meta.get("quality") or {}
    vol = np.abs(model.tet_volumes())
    tum = float(vol[np.asarray(model.region) == 2].sum())
    rows = [["Mesh", f"{model.n_nodes:,} nodes, {model.n_tets:,} tetrahedra, "
                     f"{len(model.skin):,} skin triangles, {int(model.fixed.sum()):,} "
                     "chest-wall (fixed) nodes"],
            ["Volumes", f"breast {num(vol.sum() / 1000, 0)} mL, tumour {num(tum / 1000, 2)} mL"
                        + ("" if q.get("volume_error") is None else
                           f"; mesh vs label map {num(100 * q['volume_error'], 1, signed=True)} %")]]
    if q:
        rows.append(["Element quality", f"dihedral angles {num(q.get('min_dihedral_deg'), 1)}° to "
                     f"{num(q.get('max_dihedral_deg'), 1)}°, shape quality γ min "
                     f"{num(q.get('gamma_min'), 2)}, 5th percentile {num(q.get('gamma_p5'), 2)}, "
                     f"median {num(q.get('gamma_median'), 2)}; {q.get('n_inverted', 0)} inverted"])
    lps = ", ".join(num(c, 1) for c in model.frame.origin)
    rows.append(["Nipple (LPS, mm)", f"({lps}): the origin of the model frame"])
    c = tumour_centroid(model)
    if c is not None:
        t = ", ".join(num(x, 1) for x in model.frame.to_patient(c))
        rows.append(["Tumour centroid (LPS, mm)", f"({t})"])
    return rows


def header_lines(ctx, model, results: list, prov: dict) -> list[str]:
    """The lines under the report's title: the mode that ran, the lesion predictions and the
    source of each geometry value (:func:`report_notes`), the model."""
    import textwrap

    from regtrack.report.fmt import num

    # 115 characters of 8.5 pt fit the page's 0.9 width with digits and brackets (125 ran off it)
    lines = [w for note in report_notes(results, prov) for w in textwrap.wrap(note, 115)]
    vol = np.abs(model.tet_volumes())
    tum = float(vol[np.asarray(model.region) == 2].sum())
    lines.append(f"Model: {model.n_nodes:,} nodes, {model.n_tets:,} tetrahedra, breast "
                 f"{num(vol.sum() / 1000, 0)} mL, tumour {num(tum / 1000, 2)} mL "
                 f"({model.frame.side} breast)")
    return lines


def write_report(ctx, mesh, results: list, out: Path, prov: dict) -> Path:
    """Per-view JSON and figures, the 3-D outputs, the tracking, then the PDF report."""
    from regtrack.model.checks import cut_faces
    from regtrack.report import figures as F
    from regtrack.report.export3d import write_3d_outputs
    from regtrack.report.pdf import CaseReport, Sequence, ViewReport, write_pdf
    from regtrack.report.settings import changed_settings, provenance_rows
    from regtrack.report.truth import read_truth, truth_table

    t0 = time.perf_counter()
    ctx.say("report: figures, 3-D files and PDF")
    truth = read_truth(getattr(ctx.case, "root", None))
    model = mesh.model
    views, states = [], {}
    for r in results:
        vdir = out / r.view.lower()
        _io.write_json(vdir / "virtual.json", ctx.clean(r.virtual.view.to_dict()))
        _io.write_json(vdir / "simulation.json", ctx.clean({"summary": r.sim.summary,
                                                            "steps": r.sim.steps}))
        if r.real is not None:
            _io.write_json(vdir / "real.json", ctx.clean(r.real.to_dict()))
            _io.write_json(vdir / "alignment.json", ctx.clean(r.alignment.to_dict()))
            _io.save_figure(F.overlay_figure(r.real, r.virtual.view, r.alignment), vdir / "overlay.png")
            _io.save_figure(F.images_figure(r.real, r.virtual.view, r.alignment), vdir / "images.png")
        else:
            _io.save_figure(F.virtual_figure(r.virtual.view), vdir / "virtual.png")
        for p in r.sim.pictures:
            _io.write_bytes(vdir / f"compression{p.suffix}", p.read_bytes())
        states[r.view] = step_states(r.sim)
        frame = json.loads((r.sim.folder / "result.json").read_text()).get("plate_frame")
        seq = None if frame is None or not states[r.view] else Sequence(
            model.points, model.skin, r.sim.steps[:len(states[r.view])],
            [u for _, u in states[r.view]], frame, cut_faces(model.tets, model.skin, model.fixed))
        views.append(ViewReport(r.view, r.row, r.real, r.virtual.view, r.alignment,
                                _steps_rows(r.sim.steps), [vdir / "compression.png"],
                                {"summary": r.sim.summary, "steps": r.sim.steps}, seq))
    tracked = None
    if all(r.real is not None for r in results):
        tracked = _tracking(ctx, mesh, results, out, truth)
    lesion = None if tracked is None or tracked[0].mri is None else tracked[0].mri.lps_mm
    write_3d_outputs(model, states, out, lesion_lps=lesion,
                     lesion_label="tumour centroid (MRI, tracked)")
    for p in mesh.pictures:  # model_3d.png, model_sections.png
        _io.write_bytes(out / "model" / p.name, p.read_bytes())
    appendix = []
    truth_section = None
    if truth is not None:
        res_by_view = {r.view: {"theta_p": r.row.get("theta_p"), "D": r.row.get("D"),
                                "force_N": r.row.get("force_N")} for r in results}
        if tracked is not None and tracked[0].mri is not None:
            for v, p in tracked[0].mri.views.items():
                res_by_view.setdefault(v, {})["tumour_xy_mm"] = p.xy_mm
        vol = np.abs(model.tet_volumes())
        head, rows = truth_table(truth, res_by_view,
                                 tumour_volume_mm3=float(vol[np.asarray(model.region) == 2].sum()),
                                 nipple_lps_mm=model.frame.origin)
        truth_section = (f"Ground truth ({', '.join(truth.files)}) against the result", head,
                         rows, [0.05, 0.36, 0.43, 0.60, 0.77], [48, 6, 26, 26, 26])
    extra = []
    if tracked is not None:
        page, on_page = _tracking_page(tracked, truth, truth_section)
        extra.append(page)
        if truth_section is not None and not on_page:
            appendix.append(truth_section)
    elif truth_section is not None:
        appendix.append(truth_section)
    appendix.append(("Patient model", ["Item", "Value"], model_rows(model), [0.05, 0.27],
                     [34, 112]))
    changed = changed_settings({name: getattr(ctx.configs, name) for name in CONFIG_FIELDS},
                               prov.get("protocol_overrides"))
    appendix.append(("Settings that differ from the defaults (all settings: provenance.json)",
                     ["Setting", "Value", "Default"], [list(c) for c in changed],
                     [0.05, 0.47, 0.72], [62, 36, 36]))
    appendix.append(("Provenance", ["Item", "Value"],
                     [list(r) for r in provenance_rows(prov)], [0.05, 0.27], [34, 112]))
    rep = CaseReport(ctx.case.id, ctx.case.title, views,
                     header=header_lines(ctx, model, results, prov),
                     appendix=appendix, extra_pages=extra)
    path = write_pdf(rep, out / "report.pdf")
    ctx.timings["report"] = ctx.timings.get("report", 0.0) + time.perf_counter() - t0
    return path


def _tracking_page(tracked, truth, truth_section):
    """The tracking page's drawing function, and whether it carries the truth table (in
    the space the tracking text leaves above the panels, when the table fits there)."""
    import textwrap

    from regtrack.report.pages import flow_table
    from regtrack.tracking.figures import draw_tracking_page, summary_lines

    res, reals = tracked
    txy = None if truth is None else truth.tumour_xy()
    n = len([w for ln in summary_lines(res) for w in (textwrap.wrap(ln, 115) or [""])][:22])
    top = 0.92 - 0.0105 * n - 0.03  # below the tracking text (7 pt lines)
    fits = truth_section is not None and top - 0.03 - 0.0165 * (len(truth_section[2]) + 1) > 0.58

    def draw(fig) -> None:
        draw_tracking_page(fig, res, reals, truth=txy)
        if fits:
            flow_table(fig, top, *truth_section[:3], x=truth_section[3], wrap=truth_section[4])
    return draw, fits


def _tracking(ctx, mesh, results: list, out: Path, truth):
    """Where the MRI tumour lands in each real mammogram: ``tracking.json`` and the
    result with the real views (None without a tumour in the model)."""
    from regtrack.tracking.figures import report_section
    from regtrack.tracking.mri_to_view import track_tumour
    from regtrack.tracking.viewmap import viewmap_from_outcome
    from regtrack.tracking.track import TrackResult

    if int(mesh.model.tumour_id.max(initial=0)) < 1:
        return None
    # the registration and uncertainty of the lesion prediction (lesions.json, the summary page)
    vms = {r.view: viewmap_from_outcome(r, config=ctx.configs.tracking) for r in results}
    res = TrackResult(results[0].row["case_id"], views={v: {} for v in vms},
                      mri=track_tumour(mesh.model, vms,
                                       truth=None if truth is None else truth.tumour_xy()))
    _io.write_json(out / "tracking.json", report_section(res))
    return res, {r.view: r.real for r in results}


def report_notes(results: list, prov: dict) -> list[str]:
    """The lines under the report's title: the mode, each lesion prediction (mm of the real
    canonical frame, DICOM pixels, 1-sigma radius) and, per view, where each geometry value
    (plate gap, MLO angle, projection, compression force) came from."""
    mode = prov.get("mode")
    lines = []
    if mode is not None:
        what = {"paper": "paper (tumour outlines given: registration on breast and tumour; the "
                         "lesion is also predicted from the breast alone and checked against "
                         "the outline)",
                "tracking": "tracking (no tumour outline: registration on the breast outline "
                            "and nipple; the MRI lesion predicted)",
                "mixed": "mixed (paper mode where a view has a tumour outline, tracking where "
                         "it has none)"}[mode]
        lines.append(f"Mode: {what}")
    for r in results:
        for p in r.extra.get("lesions") or []:
            px = ("" if p.centroid_px is None
                  else f", pixel (row {p.centroid_px[0]:.0f}, column {p.centroid_px[1]:.0f})")
            err = "" if p.error_mm is None else f"; {p.error_mm:.1f} mm from the outline's centroid"
            notes = "".join(f"; {n}" for n in p.notes)
            lines.append(f"{r.view} lesion {p.lesion}: ({p.centroid_mm[0]:.1f}, "
                         f"{p.centroid_mm[1]:.1f}) mm{px} ± {p.sigma_mm:.1f} mm (1σ){err}{notes}")
    labels = {"final_plate_gap": "plate gap", "plate_angle": "plate angle",
              "projection": "projection", "compression_force": "compression force"}
    for view, geo in (prov.get("geometry") or {}).items():
        parts = []
        for key, label in labels.items():
            item = geo.get(key)
            if not isinstance(item, dict) or "source" not in item:
                continue
            if key == "plate_angle" and view != "MLO":
                continue
            val = item.get("value")
            shown = "" if val is None else f" {val:g}" if isinstance(val, float) else f" {val}"
            unit = f" {item['unit']}" if item.get("unit") and val is not None else ""
            parts.append(f"{label}{shown}{unit} ({item['source']})")
        if parts:
            lines.append(f"{view} geometry: " + "; ".join(parts))
    return lines
