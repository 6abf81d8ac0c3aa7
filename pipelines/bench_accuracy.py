"""Accuracy of regtrack on the CalculiX ground-truth cases (issue 52, item 4).

Runs ``regtrack run`` at its defaults on the cases written by
``pipelines/make_truth_cases.py`` and compares with the hidden truth (which regtrack never
reads):

* ``<case>_paper``      (rotated DICOMs + true tumour outline): paper mode; theta error =
  theta_p - the truth's in-plane rotation, and d_T;
* ``<case>_paper_rot0`` (the same case, unrotated): the frame check; theta_p there is the
  registration's own bias, and theta_p(rot) - theta_p(rot0) - rotation isolates the frame;
* ``<case>_track``      (rotated DICOMs, no outline): tracking mode; the predicted lesion
  centroid (``lesions.json``, DICOM pixels) against the true lesion centroid, in mm on the
  detector (pixel spacing of the DICOM): the truth tumour's volume centroid carried by
  its displacement field and projected (:func:`truth_centroid`), the point regtrack
  predicts.  The error against the area centroid of the truth's outline as the image
  shows it is reported beside it (``lesion_error_track_outline_mm``); the two differ where
  the image's edge cuts the lesion.  The regtrack lesion is
  matched to the truth tumour by its MRI centroid (``mri_lps_mm``), never by the image;
  :func:`error_parts` splits that error into the nipple found on the mammogram, the
  registration's rotation and the rest (the mechanics and the projection);
* ``<case>_track_marked``, ``<case>_paper_marked``, ``<case>_paper_rot0_marked``
  (``--variants track_marked,paper_marked,paper_rot0_marked``, not run by default): those
  cases with the truth's nipple given on the MRI and the mammograms (:func:`marked_case`):
  the tracking error and theta error without the nipple detection;
* ``<case>_track_c1`` / ``<case>_track_nu`` (``--variants track_c1,track_nu``, not run by
  default): the tracking case with the tissue's c1 or nu moved by its 1-sigma
  (``[tracking] c1_rel_sigma``, ``nu_sigma``; :func:`sensitivity_sets`).  They measure the
  model term of the lesion sigma: how far the predicted centroid moves, against the
  stated ``alpha |Delta|`` of :func:`regtrack.tracking.uncertainty.prediction_sigma`
  (:func:`model_sensitivity`).  Nothing is compared with the truth.

Writes ``accuracy.csv`` and ``accuracy.md`` (per case and view, with medians) under
``--out``; ``sensitivity.csv`` / ``.md`` when the sensitivity variants ran; with
``--field``, ``field.md``: the two models' displacement fields compared at common material
points, by distance from the chest wall (:func:`field_difference`), a diagnostic of where
the mechanics differ.

Usage::

    .venv/bin/python pipelines/bench_accuracy.py [--root reports/truth] [--only pel03R,...]
        [--variants paper,paper_rot0,track] [--views CC] [--collect-only] [--field]
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("bench_accuracy")
REPO = Path(__file__).resolve().parents[1]
VARIANTS = ("paper", "paper_rot0", "track")
#: not run by default: the cases with the nipple marked on the MRI and on every
#: mammogram, as a user can click it (:func:`marked_case`), and the sensitivity variants
EXTRA_VARIANTS = ("track_marked", "paper_marked", "paper_rot0_marked", "track_c1", "track_nu")
#: the sensitivity variants: the perturbation of regtrack.tracking.sensitivity they apply
SENSITIVITY = {"track_c1": "c1", "track_nu": "nu"}


def run_case(case: Path, out: Path, cache: Path, timeout: int, views: str | None = None,
             sets: list[str] | None = None) -> dict:
    """``regtrack run`` at the defaults (or with ``--set`` of each of ``sets``); returns
    {rc, seconds, log tail}.

    When the run of both views fails, each view is run alone (``--views``; the stage cache
    re-uses the simulations) into ``<out>_<view>``, so that one failing view does not hide
    the other; :func:`_metrics` merges them."""
    out.mkdir(parents=True, exist_ok=True)
    if (out / "metrics.json").exists():
        return {"rc": 0, "seconds": None, "reused": True}
    cmd = [str(REPO / ".venv" / "bin" / "regtrack"), "run", str(case), "--out", str(out), "--cache", str(cache),
           "--no-report", "--serial-views"] + (["--views", views] if views else [])
    for st in sets or []:
        cmd += ["--set", st]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as fh:
        try:
            pr = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, timeout=timeout)
            rc = pr.returncode
        except subprocess.TimeoutExpired:
            rc = 124
    dt = time.perf_counter() - t0
    tail = (out.parent / f"{out.name}.log").read_text(errors="replace").splitlines()[-3:]
    log.info("%s%s: rc %d in %.0f s", case.name, f" ({views})" if views else "", rc, dt)
    res = {"rc": rc, "seconds": dt, "tail": tail}
    if rc != 0 and views is None:
        res["per_view"] = {v: run_case(case, out.parent / f"{out.name}_{v}", cache, timeout, views=v,
                                       sets=sets)
                           for v in ("CC", "MLO")}
    return res


def _outs(out: Path) -> list[Path]:
    """The run folder, or the per-view folders when the two-view run failed."""
    if (out / "metrics.json").exists():
        return [out]
    return [p for p in (out.parent / f"{out.name}_CC", out.parent / f"{out.name}_MLO")
            if (p / "metrics.json").exists()]


def _metrics(out: Path) -> dict:
    res = {}
    for o in _outs(out):
        res.update({v["view"]: v for v in json.loads((o / "metrics.json").read_text())["views"]})
    return res


def _lesions(out: Path) -> dict:
    res = {}
    for o in _outs(out):
        f = o / "lesions.json"
        if f.exists():
            res.update({v: d.get("lesions", []) for v, d in json.loads(f.read_text())["views"].items()})
    return res


def _errors(out: Path) -> dict:
    """The last 'error:' line of each failed run's log, by view (or 'both')."""
    res = {}
    for suffix, key in (("", "both"), ("_CC", "CC"), ("_MLO", "MLO")):
        lg = out.parent / f"{out.name}{suffix}.log"
        if lg.exists() and not (out.parent / f"{out.name}{suffix}" / "metrics.json").exists():
            err = [ln for ln in lg.read_text(errors="replace").splitlines() if "error" in ln.lower()]
            if err:
                res[key] = err[-1].strip()
    return res


def truth_centroid(tumour: dict) -> np.ndarray:
    """(row, col) of a truth tumour's centroid on its DICOM: its volume centroid carried by
    the truth's displacement field and projected through its cone beam
    (``volume_centroid_projected_dicom_rc``), the same point regtrack predicts (the
    lesion's mass centroid carried by its own deformation and projected).  The area
    centroid of the projected outline (``centroid_dicom_rc``) is what an outline drawn on
    the image gives; it is a different point where the lesion's projection is not
    symmetric, and a biased one where the image's edge cuts the lesion (truth files made
    before the volume centroid was stored: that one)."""
    return np.asarray(tumour.get("volume_centroid_projected_dicom_rc") or tumour["centroid_dicom_rc"],
                      float)


def match_lesion(lesions: list, truth_tumour: dict) -> dict | None:
    """The regtrack lesion whose MRI centroid is nearest the truth tumour's (MRI side only)."""
    best, bd = None, np.inf
    for le in lesions:
        m = le.get("mri_lps_mm")
        if m is None:
            continue
        d = float(np.linalg.norm(np.asarray(m) - np.asarray(truth_tumour["centroid_lps_mm"])))
        if d < bd:
            best, bd = le, d
    if best is not None:
        best = dict(best, mri_match_mm=bd)
    return best


def marked_case(root: Path, name: str, truth: dict, dst: Path, source: str = "track") -> Path:
    """``<case>_<source>`` with the nipple given: ``[mri] nipple_lps_mm`` (the truth's
    nipple, the apex of its surface) and ``[views.<V>] nipple_px`` (its projection on each
    DICOM; the unrotated one for ``paper_rot0``), as a radiologist marks it on both images.
    The truth's breast has no nipple to see, so regtrack detects its own on each image (a
    cap centre on the MRI skin, the contour point farthest from the chest wall on the
    mammogram), and the two detections need not be the same material point; these
    variants measure the tracking and the rotation without that ambiguity."""
    src = root / "cases" / f"{name}_{source}"
    views = truth["views_rot0"] if source == "paper_rot0" else truth["views"]
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    lines = (src / "case.toml").read_text().splitlines()
    n = truth["mesh"]["nipple_lps_mm"]
    out, view = [], None
    for ln in lines:
        out.append(ln.replace(f'id = "{name}_{source}"', f'id = "{name}_{source}_marked"'))
        if ln.strip() == "[mri]":
            out.append(f"nipple_lps_mm = [{n[0]:.3f}, {n[1]:.3f}, {n[2]:.3f}]")
        if ln.strip().startswith("[views."):
            view = ln.strip()[7:-1]
            rc = views[view]["nipple_dicom_rc"]
            out.append(f"nipple_px = [{rc[0]:.2f}, {rc[1]:.2f}]")
    (dst / "case.toml").write_text("\n".join(out) + "\n")
    return dst


def sensitivity_sets(case: Path, variant: str) -> list[str]:
    """``--set`` arguments of a sensitivity variant: the 1-sigma perturbation of its
    parameter as :func:`regtrack.tracking.sensitivity.perturbations` makes it from the
    case's own settings (c1 times ``1 + c1_rel_sigma``, nu minus ``nu_sigma``)."""
    from regtrack.case import load_case, resolve_configs
    from regtrack.tracking.sensitivity import perturbations

    over = perturbations(resolve_configs(load_case(case, deep=False)), "CC", None)[SENSITIVITY[variant]]
    return [f"{sec}.{k}={v:.6g}" for sec, tab in over.items() for k, v in tab.items()]


def model_sensitivity(base: list | None, moved: dict[str, list | None]) -> list[dict]:
    """Per lesion of ``base`` (``lesions.json`` of the tracking run): how far each
    perturbed run moved its predicted centroid (mm, on the same mammogram), their
    quadrature sum ``model_shift_mm``, the compression shift ``|Delta|``
    (``inplane_shift_mm``), the stated model term ``sigma_model_mm`` and the measured
    ``alpha_measured = model_shift_mm / |Delta|`` that would make the two equal."""
    out = []
    for le in base or []:
        row = {"lesion": le["lesion"], "inplane_shift_mm": le["inplane_shift_mm"],
               "sigma_model_mm": le["uncertainty_terms_mm"].get("model")}
        parts = []
        for name, lesions in moved.items():
            m = next((x for x in lesions or [] if x["lesion"] == le["lesion"]), None)
            d = None if m is None else float(np.linalg.norm(np.subtract(m["centroid_mm"], le["centroid_mm"])))
            row[f"shift_{name}_mm"] = d
            parts.append(d)
        if parts and None not in parts:
            row["model_shift_mm"] = float(np.hypot.reduce(parts))
            if le["inplane_shift_mm"] > 0:
                row["alpha_measured"] = row["model_shift_mm"] / le["inplane_shift_mm"]
        out.append(row)
    return out


#: bands of distance anterior of the chest wall (mm) of :func:`band_table`
FIELD_BANDS_MM = (0.0, 20.0, 40.0, 60.0, np.inf)


def band_table(anterior_mm: np.ndarray, u_truth: np.ndarray, u_regtrack: np.ndarray,
               bands=FIELD_BANDS_MM) -> list[dict]:
    """Per band of distance from the chest wall: the number of points, each model's mean
    displacement and the mean and RMS of their difference (regtrack - truth), mm."""
    rows = []
    d = u_regtrack - u_truth
    for lo, hi in itertools.pairwise(bands):
        s = (anterior_mm >= lo) & (anterior_mm < hi)
        if s.any():
            rows.append({"band_mm": (lo, hi), "n": int(s.sum()), "u_truth": u_truth[s].mean(0),
                         "u_regtrack": u_regtrack[s].mean(0), "mean_diff": d[s].mean(0),
                         "rms_diff": float(np.sqrt((d[s] ** 2).sum(1).mean()))})
    return rows


def field_difference(root: Path, name: str, view: str, case: Path, cache: Path,
                     target_tets: int = 1200) -> list[dict]:
    """The truth's and regtrack's displacement (LPS mm) at common material points: the
    corner centroids of the truth's tet10 that lie in regtrack's MRI breast, carried by the
    truth's field (its mesh rebuilt by ``make_truth_cases``, which must give the node
    count of its CalculiX run: ``target_tets`` as there) and by regtrack's simulation of
    ``view`` from the stage cache (never simulated here), by :func:`band_table`."""
    import importlib.util

    from regtrack.tracking.compressed import open_compressed

    spec = importlib.util.spec_from_file_location("make_truth_cases", REPO / "pipelines" / "make_truth_cases.py")
    mt = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mt
    spec.loader.exec_module(mt)
    exam, side = name[3:-1], name[-1]
    truth = json.loads((root / "truth" / f"{name}.json").read_text())
    work, origin = root / "work" / name, None
    if "mesh" in truth["views"][view]["simulation"]:  # run on the refined mesh (make_truth_cases)
        work, origin = work / "refined1", np.asarray(truth["mesh"]["nipple_lps_mm"])
        target_tets = round(target_tets * mt.REFINE)
    mesh = mt.build_mesh(mt.breast_geometry(exam, side), side, target_tets, origin_lps=origin)
    u = np.load(work / f"ccx_{view.lower()}.npz")["u"]
    if len(u) != mesh["n_nodes"]:
        raise RuntimeError(f"{name}: the rebuilt truth mesh has {mesh['n_nodes']} nodes, its "
                           f"CalculiX run {len(u)}; give the --target-tets of make_truth_cases")
    B, o, x = mesh["basis"], mesh["origin_lps"], mesh["x"]
    cen = x[mesh["tets"][:, :4]].mean(1)
    dmap = open_compressed(case, view, cache_dir=cache, simulate=False).dmap
    lps = o + cen @ B
    # NaN outside regtrack's breast (the two surfaces differ by about a voxel): left out
    moved = dmap.frame.to_patient(dmap.forward_model(dmap.frame.to_model(lps)))
    keep = np.isfinite(moved).all(axis=1)
    cen = cen[keep]
    u_truth = mt.deform_points(mesh, u, cen) @ B - cen @ B
    u_reg = moved[keep] - lps[keep]
    return band_table(cen[:, 0] - x[:, 0].min(), u_truth, u_reg)


def write_field(res: dict[tuple[str, str], list[dict]], out: Path) -> None:
    """``field.md``: :func:`field_difference` per case-view."""
    def v(a):
        return "(" + ", ".join(f"{c:+.1f}" for c in a) + ")"
    lines = [("Displacement (mm, LPS axes: x left, y posterior, z superior) of common material points, "
              "by distance anterior of the chest wall; difference = regtrack - truth."), "",
             "| case | view | band (mm) | points | truth mean u | regtrack mean u | mean difference | RMS difference |",
             "|---|---|---|---|---|---|---|---|"]
    for key, rows in res.items():
        for r in rows:
            lo, hi = r["band_mm"]
            lines.append(f"| {key[0]} | {key[1]} | {lo:.0f}-{'' if np.isinf(hi) else f'{hi:.0f}'} | {r['n']} | "
                         f"{v(r['u_truth'])} | {v(r['u_regtrack'])} | {v(r['mean_diff'])} | {r['rms_diff']:.1f} |")
    (out / "field.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _canonical_mm(rc, tv: dict, side: str) -> np.ndarray:
    """DICOM (row, col) -> canonical (x, y) mm (chest wall left, y down): undo the IHE flip
    of a right breast, then scale by the pixel spacing."""
    from regtrack.phantom.dicom_mg import canonical_to_stored_rc

    c = canonical_to_stored_rc(np.asarray(rc, float), shape=tuple(tv["image_shape"]), laterality=side)
    return c[::-1] * tv["pixel_mm"]


def error_parts(lesion: dict, tumour: dict, tv: dict, side: str) -> dict:
    """The tracking error split by its source (canonical mm, x towards the nipple, y down).

    regtrack places a lesion at ``c = n_r + R(theta_p,b) (v - n_v)``: its virtual position
    ``v`` relative to the virtual nipple, turned by the registration and put at the nipple
    ``n_r`` it found on the mammogram.  ``nipple_error_mm`` is ``|n_r - n|`` against the
    true projected nipple ``n``.  ``lesion_error_true_theta_mm``: the prediction with the
    true rotation and the true nipple, ``n + R(theta - theta_p,b) (c - n_r)``, against the
    true lesion: what is left is the mechanics and the projection.
    ``lesion_error_x_mm`` / ``_y_mm``: that error along the chest wall -> nipple axis and
    across it.  ``lesion_r_true_mm``: the true lesion's distance from the nipple.  Without
    regtrack's nipple in ``lesions.json`` the true one stands for it."""
    from regtrack.registration.geometry import rotation

    c = _canonical_mm(lesion["centroid_px_rc"], tv, side)
    t = _canonical_mm(truth_centroid(tumour), tv, side)
    n = _canonical_mm(tv["nipple_dicom_rc"], tv, side)
    nr = n if lesion.get("nipple_px_rc") is None else _canonical_mm(lesion["nipple_px_rc"], tv, side)
    th = lesion.get("theta_p_b_deg")
    if th is None:
        return {}
    e = (rotation(tv["rotation_deg"] - th) @ (c - nr) + n) - t
    return {"lesion_error_true_theta_mm": float(np.linalg.norm(e)), "lesion_error_x_mm": float(e[0]),
            "lesion_error_y_mm": float(e[1]), "lesion_r_true_mm": float(np.linalg.norm(t - n)),
            "theta_error_b_track_deg": float(th - tv["rotation_deg"]),
            "nipple_error_mm": float(np.linalg.norm(nr - n))}


def _median(vals):
    v = [x for x in vals if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else None


def _tracking_columns(lesions: list | None, tv: dict, side: str, suffix: str) -> dict:
    """The tracking error of the largest truth tumour in one view and its parts
    (:func:`error_parts`), each column name ending in ``suffix``."""
    row: dict = {"lesion_error_track_mm": None}
    if tv["tumours"] and lesions:
        tt = tv["tumours"][0]  # the largest tumour
        le = match_lesion(lesions, tt)
        if le is not None:
            c = np.asarray(le["centroid_px_rc"], float)
            row.update({"lesion_error_track_mm": float(np.linalg.norm(c - truth_centroid(tt)) * tv["pixel_mm"]),
                        "lesion_error_track_outline_mm":
                            float(np.linalg.norm(c - np.asarray(tt["centroid_dicom_rc"])) * tv["pixel_mm"]),
                        "lesion_notes": "; ".join(le.get("notes") or []),
                        "lesion_mri_match_mm": le["mri_match_mm"], "lesion_sigma_mm": le.get("sigma_mm"),
                        "n_lesions_regtrack": len(lesions)})
            row.update(error_parts(le, tt, tv, side))
    return {k + suffix: v for k, v in row.items()}


def collect(root: Path, name: str, truth: dict, res: Path,
            only_view: str | None = None) -> list[dict]:
    rows = []
    mp, m0, mt = (_metrics(res / f"{name}_{v}") for v in VARIANTS)
    lt = _lesions(res / f"{name}_track")
    lm = _lesions(res / f"{name}_track_marked")
    mpm, m0m = _metrics(res / f"{name}_paper_marked"), _metrics(res / f"{name}_paper_rot0_marked")
    for view, tv in truth["views"].items():
        if only_view and view != only_view:
            continue
        rot = tv["rotation_deg"]
        row = {"case": name, "view": view, "rotation_true_deg": rot,
               "D_true": tv["simulation"].get("D_reached", truth["params"]["D"][view]), "gap_true_mm": tv["simulation"]["gap_mm"],
               "angle_true_deg": tv["simulation"]["angle_deg"],
               "friction_true": truth["params"]["friction"]}
        a = mp.get(view, {})
        b = m0.get(view, {})
        g = a or mt.get(view, {})  # the geometry regtrack used (paper run, else tracking run)
        row.update({"theta_p_paper": a.get("theta_p"), "theta_p_b_paper": a.get("theta_p_b"),
                    "theta_p_t_paper": a.get("theta_p_t"), "d_T_paper": a.get("d_T"),
                    "lesion_error_paper_mm": a.get("lesion_error_mm"),
                    "D_regtrack": g.get("D"), "gap_regtrack_mm": g.get("plate_gap_mm"),
                    "gap_source": g.get("gap_source"), "projection": g.get("projection"),
                    "angle_regtrack_deg": g.get("plate_angle_deg"),
                    "BS_Av_track": mt.get(view, {}).get("BS_Av"), "d_B_track": mt.get(view, {}).get("d_B"),
                    "theta_p_rot0": b.get("theta_p"), "d_T_rot0": b.get("d_T")})
        row["theta_error_deg"] = (a["theta_p"] - rot) if a.get("theta_p") is not None else None
        row["theta_error_vs_rot0_deg"] = (a["theta_p"] - b["theta_p"] - rot) \
            if a.get("theta_p") is not None and b.get("theta_p") is not None else None
        am, bm = mpm.get(view, {}), m0m.get(view, {})
        row["theta_error_deg_marked"] = (am["theta_p"] - rot) if am.get("theta_p") is not None else None
        row["theta_p_rot0_marked"] = bm.get("theta_p")
        # tracking mode
        c = mt.get(view, {})
        row["mode_track"] = c.get("mode")
        row["theta_p_track"] = c.get("theta_p")
        row.update(_tracking_columns(lt.get(view), tv, truth["side"], ""))
        row.update(_tracking_columns(lm.get(view), tv, truth["side"], "_marked"))
        errs = []
        for var in VARIANTS + EXTRA_VARIANTS:
            e = _errors(res / f"{name}_{var}")
            msg = e.get(view) or (e.get("both") if view not in (_metrics(res / f"{name}_{var}")) else None)
            if msg:
                errs.append(f"{var}: {msg}")
        row["regtrack_errors"] = " | ".join(errs)
        rows.append(row)
    return rows


COLS = ["case", "view", "rotation_true_deg", "theta_p_paper", "theta_error_deg", "theta_p_rot0",
        "theta_error_vs_rot0_deg", "d_T_paper", "lesion_error_paper_mm", "lesion_error_track_mm",
        "lesion_error_track_outline_mm", "lesion_notes", "lesion_sigma_mm", "lesion_error_true_theta_mm",
        "lesion_error_x_mm", "lesion_error_y_mm",
        "lesion_r_true_mm", "theta_error_b_track_deg", "nipple_error_mm", "lesion_error_track_mm_marked",
        "lesion_sigma_mm_marked", "lesion_error_true_theta_mm_marked", "theta_error_b_track_deg_marked",
        "nipple_error_mm_marked", "theta_error_deg_marked", "theta_p_rot0_marked", "n_lesions_regtrack", "lesion_mri_match_mm", "D_true", "D_regtrack", "gap_true_mm",
        "gap_regtrack_mm", "gap_source", "angle_true_deg", "angle_regtrack_deg", "projection", "friction_true",
        "theta_p_b_paper", "theta_p_t_paper", "theta_p_track", "mode_track", "BS_Av_track", "d_B_track",
        "d_T_rot0", "regtrack_errors"]


def write_tables(rows: list[dict], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "accuracy.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)

    def f(x, nd=2):
        return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))

    show = ["case", "view", "rotation_true_deg", "theta_p_paper", "theta_error_deg", "theta_p_rot0",
            "theta_error_vs_rot0_deg", "d_T_paper", "lesion_error_track_mm",
            "lesion_error_track_outline_mm", "lesion_sigma_mm", "lesion_error_true_theta_mm",
            "lesion_error_x_mm", "lesion_error_y_mm", "lesion_error_paper_mm",
            "D_true", "D_regtrack", "angle_true_deg", "angle_regtrack_deg"]
    lines = ["| " + " | ".join(show) + " |", "|" + "---|" * len(show)]
    for r in rows:
        lines.append("| " + " | ".join(f(r.get(k)) for k in show) + " |")
    med = {k: _median([r.get(k) for r in rows]) for k in ("theta_error_deg", "theta_error_vs_rot0_deg",
                                                            "d_T_paper", "lesion_error_track_mm",
                                                            "lesion_error_track_outline_mm",
                                                            "lesion_error_paper_mm", "theta_p_rot0",
                                                            "lesion_error_true_theta_mm",
                                                            "lesion_error_track_mm_marked",
                                                            "theta_p_rot0_marked")}
    absmed = _median([abs(r["theta_error_deg"]) for r in rows if r.get("theta_error_deg") is not None])
    absmed_m = _median([abs(r["theta_error_deg_marked"]) for r in rows
                        if r.get("theta_error_deg_marked") is not None])
    def worst_of(k):
        return max([r[k] for r in rows if r.get(k) is not None], default=None)

    worst, worst_o = worst_of("lesion_error_track_mm"), worst_of("lesion_error_track_outline_mm")
    lines += ["", f"Medians over {len(rows)} case-views: |theta error| {f(absmed)} deg (signed {f(med['theta_error_deg'])}), "
              f"theta_p on the unrotated copy {f(med['theta_p_rot0'])} deg, d_T {f(med['d_T_paper'])} mm, "
              f"tracking-mode lesion centroid error {f(med['lesion_error_track_mm'])} mm (worst {f(worst)} mm), "
              f"against the area centroid of the outline the image shows "
              f"{f(med['lesion_error_track_outline_mm'])} mm (worst {f(worst_o)} mm), "
              f"paper-mode lesion error {f(med['lesion_error_paper_mm'])} mm; "
              f"tracking error with the true rotation {f(med['lesion_error_true_theta_mm'])} mm; "
              f"tracking with the nipple marked {f(med['lesion_error_track_mm_marked'])} mm; "
              f"with the nipple marked, |theta error| {f(absmed_m)} deg and theta_p on the unrotated "
              f"copy {f(med['theta_p_rot0_marked'])} deg."]
    (out / "accuracy.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


SENS_COLS = ["case", "view", "lesion", "inplane_shift_mm", "shift_c1_mm", "shift_nu_mm", "model_shift_mm",
             "sigma_model_mm", "alpha_measured"]


def write_sensitivity(rows: list[dict], out: Path) -> None:
    """``sensitivity.csv`` / ``.md``: the measured model term per lesion, with medians."""
    with open(out / "sensitivity.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=SENS_COLS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    lines = ["| " + " | ".join(SENS_COLS) + " |", "|" + "---|" * len(SENS_COLS)]
    for r in rows:
        lines.append("| " + " | ".join("-" if r.get(k) is None else
                                       (f"{r[k]:.2f}" if isinstance(r[k], float) else str(r[k]))
                                       for k in SENS_COLS) + " |")
    med = {k: _median([r.get(k) for r in rows]) for k in ("model_shift_mm", "sigma_model_mm", "alpha_measured")}
    m = {k: "-" if v is None else f"{v:.2f}" for k, v in med.items()}
    lines += ["", (f"Medians over {len(rows)} lesions: measured model shift {m['model_shift_mm']} mm, "
                   f"stated model term {m['sigma_model_mm']} mm, alpha measured {m['alpha_measured']}.")]
    (out / "sensitivity.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", default="reports/truth", help="make_truth_cases.py --out")
    ap.add_argument("--out", default=None, help="results folder (default ROOT/bench)")
    ap.add_argument("--only", default="", help="comma-separated case names, e.g. pel03R")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help=f"of {', '.join(VARIANTS + EXTRA_VARIANTS)}")
    ap.add_argument("--collect-only", action="store_true", help="do not run regtrack; tabulate what exists")
    ap.add_argument("--timeout", type=int, default=3600)
    ap.add_argument("--field", action="store_true",
                    help="also compare the displacement fields of the tracking runs (field.md)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="a case.toml setting for every run (regtrack run --set), e.g. to "
                         "measure one registration setting against the default; give --out "
                         "and --cache so that the default's results are kept and its "
                         "simulations re-used")
    ap.add_argument("--views", default=None, type=str.upper, choices=("CC", "MLO"),
                    help="one view (CC or MLO) to run and tabulate, e.g. where the other "
                         "view's truth is not usable (default: every view of the truth)")
    ap.add_argument("--cache", default=None,
                    help="stage caches' folder (default OUT/cache): another run's, to re-use "
                         "its simulations")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    root = Path(a.root)
    res = Path(a.out) if a.out else root / "bench"
    caches = Path(a.cache) if a.cache else res / "cache"
    names = sorted(p.stem for p in (root / "truth").glob("*.json"))
    if a.only:
        keep = set(a.only.split(","))
        names = [n for n in names if n in keep]
    variants = [v for v in a.variants.split(",") if v]
    runs = {}
    rows, sens, field = [], [], {}
    for name in names:
        truth = json.loads((root / "truth" / f"{name}.json").read_text())
        if not a.collect_only:
            for v in variants:
                case = (marked_case(root, name, truth, res / "cases" / f"{name}_{v}",
                                    v.removesuffix("_marked"))
                        if v.endswith("_marked") else root / "cases" / f"{name}_{v}")
                sets = list(a.set)
                if v in SENSITIVITY:
                    case = root / "cases" / f"{name}_track"
                    sets += sensitivity_sets(case, v)
                runs[f"{name}_{v}"] = run_case(case, res / f"{name}_{v}", caches / name, a.timeout,
                                               views=a.views, sets=sets)
        rows += collect(root, name, truth, res, a.views)
        if a.field:
            for view in [v for v in truth["views"] if a.views in (None, v)]:
                field[(name, view)] = field_difference(root, name, view, root / "cases" / f"{name}_track",
                                                       caches / name)
        base = _lesions(res / f"{name}_track")
        moved = {v: _lesions(res / f"{name}_{v}") for v in SENSITIVITY}
        for view in base:
            if any(m for m in moved.values()):
                sens += [{"case": name, "view": view} | r for r in model_sensitivity(
                    base[view], {SENSITIVITY[v]: m.get(view) for v, m in moved.items()})]
    (res).mkdir(parents=True, exist_ok=True)
    if runs:
        (res / "runs.json").write_text(json.dumps(runs, indent=1))
    write_tables(rows, res)
    if sens:
        write_sensitivity(sens, res)
    if field:
        write_field(field, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
