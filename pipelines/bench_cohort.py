"""Cohort benchmark: ``regtrack mesh`` and CC + MLO ``regtrack simulate`` on every Pelicano exam.

For every exam of ``../shared/data/pelicano`` (Pelicano et al., Sensors 2021 / PLoS One
2024) the breast holding the larger tumour volume is meshed at the defaults (both breasts
where both hold a tumour), and each model is compressed in the selected views at the
protocol defaults (D = 38 % CC, 28 % MLO, 26 % biopsy) and at D = 50 %.  ``--views biopsy
--D 0.12 0.26 0.32`` gives the MR-biopsy cohort table of issue 55.  Every stage runs as its own
``python -m regtrack.cli`` child process, ``--jobs`` of them at a time (default: one per
core), each killed after ``--timeout`` seconds; a failed or killed run is recorded and the
benchmark goes on.  Usage::

    .venv/bin/python pipelines/bench_cohort.py [--exams 02 03] [--views cc mlo]
        [--D default 0.5] [--target-nodes N] [--jobs N] [--timeout S] [--mesh-only]
        [--out DIR]

Writes to ``--out`` (default ``reports/cohort``): ``meshing.csv`` / ``meshing.md`` (one row
per model) and ``simulation.csv`` / ``simulation.md`` (one row per model, view and D, plus
the median and worst per view), and every run's files and log under ``runs/``.

What is read from the children (nothing else: the solver's internals may change):

* ``regtrack mesh``: its exit code and the model sidecar ``model.json``, ``meta.quality``
  (``n_nodes``, ``n_tets``, ``min_dihedral_deg``, ``gamma_p5``, ``volume_error``,
  ``tumours[*].volume_error`` / ``voxel_volume_mm3``), ``meta.attempts`` (the last one's
  ``attempt`` and ``tumour_refinement``: the attempt of the plan used and its tumour
  refinement rounds; their count: the gmsh runs) and
  ``meta.preparation.tumour_volume_by_side_mm3`` (to mesh the other breast too);
* ``regtrack simulate``: its exit code and the result JSON's ``summary`` fields
  ``complete``, ``D``, ``upper_force_N``, ``force_imbalance_rel``, ``iterations``,
  ``max_penetration_mm``, ``skin_overlap_mm`` (the deepest skin node inside the tissue,
  :mod:`regtrack.mechanics.overlap`), ``plate_gap_mm``, the plate normal of ``plate_frame`` and the
  top-level ``error``; from the model, the fixed (chest-wall) nodes, for the height of the
  chest-wall section along the plate normal over the final gap (``wall_section_to_gap``).  Every field is optional: a missing
  one is left empty in the table.

Wall seconds are measured here; CPU seconds and peak memory come from ``os.wait4`` on the
child (user + system time of the child and its descendants; ``ru_maxrss``: the resident set
of the largest process of its tree, which counts the forking benchmark's own few tens of MB
until the child's ``exec``).  Each child gets ``OMP_NUM_THREADS`` /
``MKL_NUM_THREADS`` = ``--threads`` (default: cores // jobs), so ``--jobs`` children do not
oversubscribe the cores.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PELICANO = REPO.parent / "shared" / "data" / "pelicano"
CITATION = "Pelicano et al., Sensors 2021 / PLoS One 2024 (breast models, Hospital da Luz, Lisbon)"


@dataclass
class Run:
    """Outcome of one child process."""

    rc: int | None  # None: killed at the timeout
    wall_s: float
    cpu_s: float
    peak_rss_mb: float
    log: Path
    error: str = ""


def run_child(args: list[str], *, log: Path, timeout_s: float, threads: int) -> Run:
    """Run ``python -m regtrack.cli ARGS`` in its own session, killed (whole process group)
    after ``timeout_s``; stdout and stderr go to ``log``."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads),
               OPENBLAS_NUM_THREADS=str(threads), PYTHONPATH=str(REPO))
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "regtrack.cli", *args], stdout=fh,
                                stderr=subprocess.STDOUT, cwd=REPO, env=env, start_new_session=True)
        killed = False
        while True:
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout_s and not killed:
                os.killpg(proc.pid, signal.SIGKILL)
                killed = True
            time.sleep(0.2)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    run = Run(None if killed else proc.returncode, wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024.0, log)
    if killed:
        run.error = f"killed after the {timeout_s:g} s timeout"
    elif proc.returncode:
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
        run.error = lines[-1] if lines else f"exit code {proc.returncode}"
    return run


def exam_label_map(exam_dir: Path) -> Path | None:
    """The simple label map of an exam (the case of the file name varies)."""
    found = [p for p in exam_dir.iterdir() if "simple" in p.name.lower()]
    return found[0] if found else None


def read_settings(path: Path | None) -> str:
    """The text of a ``--settings`` TOML file (tables such as ``[contact]``) to add to every
    case of the benchmark; "" without one.  Raises ``ValueError`` (one line) when it does not
    parse or holds a table the benchmark writes itself (``case``, ``mri``, ``protocol``)."""
    if path is None:
        return ""
    import tomllib

    text = path.read_text()
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"--settings {path}: not TOML ({exc})") from None
    own = sorted(set(doc) & {"case", "mri", "protocol"})
    if own:
        raise ValueError(f"--settings {path}: [{own[0]}] is written by the benchmark; give the other "
                         "tables only (D with --D)")
    return text


def write_case(folder: Path, *, case_id: str, labels: Path, side: str | None, D: float | None,
               settings: str = "") -> Path:
    """A case folder for one breast: ``case.toml`` and a copy of the label map (a case's
    paths must lie inside its folder, links included); ``D`` sets ``target_D`` of both views,
    ``settings`` (:func:`read_settings`) is added as it is."""
    (folder / "mri").mkdir(parents=True, exist_ok=True)
    copy = folder / "mri" / labels.name
    if not copy.exists():
        shutil.copyfile(labels, copy)
    lines = ["[case]", f'id = "{case_id}"', "", "[mri]", f'labels = "mri/{labels.name}"',
             'scheme = "pelicano-simple"']
    if side:
        lines.append(f'side = "{side}"')
    if D is not None:
        for v in ("CC", "MLO", "BIOPSY"):
            lines += ["", f"[protocol.{v}]", f"target_D = {D}"]
    (folder / "case.toml").write_text("\n".join(lines) + "\n" + ("\n" + settings if settings else ""))
    return folder


def _get(doc: dict, *keys, default=None):
    for k in keys:
        if not isinstance(doc, dict) or k not in doc:
            return default
        doc = doc[k]
    return doc


@dataclass
class Model:
    exam: str
    side: str | None  # None: the default choice (read back from the model)
    labels: Path
    folder: Path
    row: dict = field(default_factory=dict)

    @property
    def vtu(self) -> Path:
        return self.folder / "out" / "model.vtu"


def mesh_model(m: Model, *, target_nodes: int | None, timeout_s: float, threads: int,
               resume: bool = False, settings: str = "") -> dict:
    """Mesh one breast and read the sidecar; returns the meshing row (kept as ``row.json``
    beside the model).  With ``resume``, a model already meshed is read back instead (its
    row, or the sidecar alone when the row was not kept: no timings then)."""
    write_case(m.folder, case_id=f"exam{m.exam}", labels=m.labels, side=m.side, D=None,
               settings=settings)
    saved = m.folder / "row.json"
    if resume and saved.is_file():
        m.row = json.loads(saved.read_text())
        m.side = m.side or m.row.get("side") or None
        return m.row
    if resume and m.vtu.is_file():
        r = Run(0, math.nan, math.nan, math.nan, m.folder / "mesh.log")
    else:
        args = ["mesh", str(m.folder), "--out", str(m.vtu), "--no-pictures"]
        if target_nodes:
            args += ["--target-nodes", str(target_nodes)]
        r = run_child(args, log=m.folder / "mesh.log", timeout_s=timeout_s, threads=threads)
    meta = {}
    if r.rc == 0 and m.vtu.with_suffix(".json").is_file():
        meta = _get(json.loads(m.vtu.with_suffix(".json").read_text()), "meta", default={}) or {}
    q = meta.get("quality", {})
    prep = meta.get("preparation", {})
    tum = q.get("tumours", []) or []
    errs = [t.get("volume_error") for t in tum if t.get("volume_error") is not None]
    m.side = m.side or prep.get("side")
    m.row = {
        "exam": m.exam, "side": m.side or "", "completed": r.rc == 0, "exit_code": r.rc,
        "nodes": q.get("n_nodes"), "tets": q.get("n_tets"),
        "min_dihedral_deg": q.get("min_dihedral_deg"), "gamma_p5": q.get("gamma_p5"),
        "volume_error": q.get("volume_error"), "tumours": len(tum),
        "tumour_ml": " ".join(f"{t.get('voxel_volume_mm3', math.nan) / 1000:.2f}" for t in tum),
        "tumour_volume_errors": " ".join(f"{e:+.4f}" for e in errs),
        "worst_tumour_volume_error": max(errs, key=abs) if errs else None,
        "attempt_used": _get((meta.get("attempts") or [{}])[-1], "attempt"),
        "meshings": len(meta.get("attempts", [])) or None,
        "tumour_refinements": _get((meta.get("attempts") or [{}])[-1], "tumour_refinement"),
        "wall_s": r.wall_s, "cpu_s": r.cpu_s, "peak_rss_mb": r.peak_rss_mb, "error": r.error,
        "_tumour_by_side": prep.get("tumour_volume_by_side_mm3") or {},
    }
    saved.write_text(json.dumps(m.row, default=str))
    return m.row


def simulate_model(m: Model, view: str, D: float | None, *, timeout_s: float, threads: int,
                   resume: bool = False, settings: str = "") -> dict:
    """Compress one model in one view (``D`` None: the protocol default); returns its row
    (kept as ``row.json`` in the run's folder; with ``resume`` a kept row is read back)."""
    tag = "default" if D is None else f"D{round(100 * D)}"
    case = write_case(m.folder / f"case_{tag}", case_id=f"exam{m.exam}{m.side}", labels=m.labels,
                      side=m.side, D=D, settings=settings)
    out = m.folder / f"sim_{tag}_{view}"
    saved = out / "row.json"
    if resume and saved.is_file():
        return json.loads(saved.read_text())
    r = run_child(["simulate", str(case), "--view", view, "--model", str(m.vtu), "--out", str(out)],
                  log=out.with_suffix(".log"), timeout_s=timeout_s, threads=threads)
    doc = {}
    js = sorted(out.glob("*.json")) if out.is_dir() else []
    if js:
        try:
            doc = json.loads(js[0].read_text())
        except (OSError, ValueError):
            doc = {}
    s = _get(doc, "summary", default={}) or {}
    err = r.error or (str(doc["error"]) if doc.get("error") else "")
    row = {
        "exam": m.exam, "side": m.side, "view": view.upper(), "D_setting": tag, "nodes": m.row.get("nodes"),
        "completed": r.rc == 0 and bool(s.get("complete", False)) and not doc.get("error"),
        "wall_section_to_gap": wall_section_to_gap(m.vtu, _get(doc, "plate_frame", "normal"),
                                                   s.get("plate_gap_mm")),
        "force_balance_rel": s.get("force_imbalance_rel"), "D": s.get("D"),
        "plate_force_N": s.get("upper_force_N"), "iterations": s.get("iterations"),
        "max_penetration_mm": s.get("max_penetration_mm"),
        "skin_overlap_mm": s.get("skin_overlap_mm"),
        "wall_s": r.wall_s, "cpu_s": r.cpu_s, "peak_rss_mb": r.peak_rss_mb, "error": err,
    }
    out.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps(row, default=str))
    return row


def wall_section_to_gap(vtu: Path, normal, gap_mm) -> float | None:
    """Height of the fixed chest-wall section along the plate normal over the final plate
    gap: above 1, the plates' chest-wall edges end up inside the fixed section, and the
    tissue between them and the fixed nodes is pinched (None when either is unknown)."""
    if normal is None or not gap_mm or not vtu.is_file():
        return None
    from regtrack.model.io import load_model

    model = load_model(vtu)
    h = model.points[model.fixed] @ np.asarray(normal, float)
    return float(np.ptp(h)) / float(gap_mm) if len(h) else None


# ---------------------------------------------------------------- tables

MESH_COLS = ["exam", "side", "completed", "nodes", "tets", "min_dihedral_deg", "gamma_p5", "volume_error",
             "tumours", "tumour_ml", "tumour_volume_errors", "worst_tumour_volume_error", "attempt_used",
             "meshings", "tumour_refinements",
             "wall_s", "cpu_s", "peak_rss_mb", "exit_code", "error"]
SIM_COLS = ["exam", "side", "view", "D_setting", "nodes", "completed", "wall_section_to_gap",
            "force_balance_rel", "D", "plate_force_N",
            "iterations", "max_penetration_mm", "skin_overlap_mm", "wall_s", "cpu_s", "peak_rss_mb",
            "error"]


def fmt(v, col: str = "") -> str:
    """One table cell: fractions as %, times to 0.1 s, None empty."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if col in ("volume_error", "worst_tumour_volume_error", "D"):
            return f"{100 * v:.1f} %"
        if col == "force_balance_rel":
            return f"{100 * v:.3g} %"
        if col == "wall_section_to_gap":
            return f"{v:.2f}"
        return f"{v:.1f}" if abs(v) >= 1 or v == 0 else f"{v:.3g}"
    return str(v).replace("|", "/")


def write_table(rows: list[dict], cols: list[str], stem: Path, extra_md: list[str] = ()) -> None:
    """``stem.csv`` (raw values) and ``stem.md`` (formatted, then ``extra_md`` lines)."""
    with open(stem.with_suffix(".csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    md = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(fmt(r.get(c), c) for c in cols) + " |" for r in rows]
    stem.with_suffix(".md").write_text("\n".join([*md, "", *extra_md]) + "\n")


def _num(rows: list[dict], key: str) -> list[float]:
    return [float(r[key]) for r in rows if isinstance(r.get(key), (int, float))
            and not isinstance(r.get(key), bool) and math.isfinite(r[key])]


def summary_lines(rows: list[dict], groups: list[str], *, worst_abs: tuple[str, ...] = ()) -> list[str]:
    """Median and worst (largest; largest magnitude for ``worst_abs``) per group of ``groups``
    keys, over the completed runs; the count of completed runs."""
    keys = sorted({tuple(r[g] for g in groups) for r in rows})
    metrics = ["nodes", "force_balance_rel", "iterations", "skin_overlap_mm", "wall_s", "cpu_s",
               "peak_rss_mb", "worst_tumour_volume_error", "volume_error"]
    out = ["| " + " | ".join(groups) + " | completed | " + " | ".join(f"{m} median / worst" for m in metrics if any(m in r for r in rows)) + " |"]
    out.append("|" + "---|" * (len(groups) + 1 + sum(any(m in r for r in rows) for m in metrics)))
    for k in keys:
        sel = [r for r in rows if tuple(r[g] for g in groups) == k]
        ok = [r for r in sel if r.get("completed")]
        cells = []
        for m in metrics:
            if not any(m in r for r in rows):
                continue
            vals = _num(ok, m)
            if not vals:
                cells.append("")
                continue
            worst = max(vals, key=abs) if m in worst_abs else max(vals)
            med = statistics.median(vals)
            cells.append(f"{fmt(med, m)} / {fmt(worst, m)}")
        out.append("| " + " | ".join(str(x) for x in k) + f" | {len(ok)} of {len(sel)} | " + " | ".join(cells) + " |")
    return out


# ---------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=PELICANO, help="folder of Exam_NN folders")
    ap.add_argument("--exams", nargs="*", default=None, help="exam numbers (default: all)")
    ap.add_argument("--views", nargs="*", default=["cc", "mlo"],
                    choices=["cc", "mlo", "biopsy"])
    ap.add_argument("--D", nargs="*", default=["default", "0.5"],
                    help="compression settings: 'default' (protocol D) and/or target D values")
    ap.add_argument("--target-nodes", type=int, default=None, help="mesh size (default: the mesher's)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="child processes at a time")
    ap.add_argument("--threads", type=int, default=None, help="threads per child (default cores // jobs)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds before a simulation is killed")
    ap.add_argument("--mesh-timeout", type=float, default=1800.0, help="seconds before a meshing is killed")
    ap.add_argument("--mesh-only", action="store_true", help="stop after meshing")
    ap.add_argument("--out", type=Path, default=REPO / "reports" / "cohort")
    ap.add_argument("--settings", type=Path, default=None,
                    help="a TOML file of tables added to every case (e.g. [contact] "
                         "self_contact_gap_mm = 0, no self-contact): the cohort off the "
                         "defaults")
    ap.add_argument("--resume", action="store_true",
                    help="re-use the models and runs of an earlier, interrupted benchmark in --out")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        ap.error(f"--data {args.data}: not a folder; the Pelicano exams are in ../shared/data/pelicano")
    try:
        settings = read_settings(args.settings)
    except (OSError, ValueError) as exc:
        ap.error(str(exc))
    jobs = max(1, args.jobs)
    threads = args.threads or max(1, (os.cpu_count() or 1) // jobs)
    Ds = [None if d == "default" else float(d) for d in args.D]
    exams = args.exams or sorted(p.name.split("_", 1)[1] for p in args.data.glob("Exam_*"))
    args.out.mkdir(parents=True, exist_ok=True)
    runs = args.out / "runs"
    lock = threading.Lock()

    def say(msg: str) -> None:
        with lock:
            print(msg, flush=True)

    models: list[Model] = []
    for e in exams:
        f = exam_label_map(args.data / f"Exam_{e}") if (args.data / f"Exam_{e}").is_dir() else None
        if f is None:
            say(f"exam {e}: no simple label map under {args.data}; skipped")
            continue
        models.append(Model(e, None, f, runs / f"exam{e}"))

    def mesh(m: Model) -> list[Model]:
        """Mesh the default breast, then the other one too when it also holds a tumour."""
        done = [m]
        mesh_model(m, target_nodes=args.target_nodes, timeout_s=args.mesh_timeout, threads=threads,
                   resume=args.resume, settings=settings)
        say(f"mesh exam {m.exam} {m.side}: {m.row['nodes']} nodes, {m.row['wall_s']:.0f} s {m.row['error']}")
        by_side = m.row.get("_tumour_by_side", {})
        if m.side and all(by_side.get(s, 0) > 0 for s in ("L", "R")):
            other = "L" if m.side == "R" else "R"
            o = Model(m.exam, other, m.labels, runs / f"exam{m.exam}{other}")
            mesh_model(o, target_nodes=args.target_nodes, timeout_s=args.mesh_timeout, threads=threads,
                       resume=args.resume, settings=settings)
            say(f"mesh exam {o.exam} {o.side}: {o.row['nodes']} nodes, {o.row['wall_s']:.0f} s {o.row['error']}")
            done.append(o)
        return done

    with ThreadPoolExecutor(jobs) as pool:
        meshed = [x for group in pool.map(mesh, models) for x in group]
    mrows = [m.row for m in meshed]
    write_table(mrows, MESH_COLS, args.out / "meshing",
                [f"Data: {CITATION}.", "", "Summary over the completed models:", "",
                 *summary_lines([{**r, "all": "all"} for r in mrows], ["all"],
                                worst_abs=("worst_tumour_volume_error", "volume_error"))])
    say(f"meshed {sum(r['completed'] for r in mrows)} of {len(mrows)} models -> {args.out / 'meshing.md'}")
    if args.mesh_only:
        return 0

    tasks = [(m, v, d) for m in meshed if m.row["completed"] for d in Ds for v in args.views]

    done: list[dict] = []

    def sim(t):
        m, v, d = t
        r = simulate_model(m, v, d, timeout_s=args.timeout, threads=threads, resume=args.resume,
                           settings=settings)
        say(f"simulate exam {m.exam} {m.side} {v} {r['D_setting']}: completed {r['completed']}, "
            f"{r['wall_s']:.0f} s {r['error']}")
        with lock:  # the table so far, so that an interrupted benchmark still has one
            done.append(r)
            write_table(done, SIM_COLS, args.out / "simulation",
                        [f"Data: {CITATION}.", "", f"Partial: {len(done)} of {len(tasks)} runs.", "",
                         *summary_lines(done, ["view", "D_setting"])])
        return r

    with ThreadPoolExecutor(jobs) as pool:
        srows = list(pool.map(sim, tasks))
    for m in meshed:  # a model that did not mesh fails every view
        if not m.row["completed"]:
            srows += [{"exam": m.exam, "side": m.side or "", "view": v.upper(),
                       "D_setting": "default" if d is None else f"D{round(100 * d)}", "completed": False,
                       "error": "meshing failed"} for d in Ds for v in args.views]
    write_table(srows, SIM_COLS, args.out / "simulation",
                [f"Data: {CITATION}.", "", "Median and worst per view (completed runs):", "",
                 *summary_lines(srows, ["view", "D_setting"])])
    say(f"simulated {sum(r['completed'] for r in srows)} of {len(srows)} runs -> {args.out / 'simulation.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
