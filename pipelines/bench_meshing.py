"""Benchmark of ``regtrack mesh`` on every Pelicano exam (and the phantom sample case).

For each exam: the breast chosen by the default rules (the one holding the tumour volume),
default :class:`MeshConfig`; reports nodes, tets, tumours kept/removed, quality, volume
errors, wall time and peak memory (resident set of this process plus its gmsh children,
sampled every 0.1 s).  Usage::

    .venv/bin/python pipelines/bench_meshing.py [--exams 02 03 ...] [--json out.json]

Data: Pelicano et al., Sensors 2021 / PLoS One 2024 (../shared/data/pelicano).
"""

from __future__ import annotations

import argparse
import glob
import json
import logging
import os
import threading
import time
from pathlib import Path

import psutil

from regtrack.errors import RegtrackError
from regtrack.imaging.readers import read_label_map
from regtrack.model.build import build_model
from regtrack.model.config import MeshConfig
from regtrack.model.labels import PRESETS

REPO = Path(__file__).resolve().parents[1]
PELICANO = REPO.parent / "shared" / "data" / "pelicano"


class PeakMemory:
    """Peak RSS (bytes) of this process and its children, sampled in a thread."""

    def __init__(self, every_s: float = 0.1):
        self.every_s, self.peak, self._stop = every_s, 0, threading.Event()

    def _run(self):
        me = psutil.Process()
        while not self._stop.is_set():
            try:
                rss = me.memory_info().rss + sum(c.memory_info().rss for c in me.children(recursive=True))
            except psutil.Error:
                rss = 0
            self.peak = max(self.peak, rss)
            time.sleep(self.every_s)

    def __enter__(self):
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()


def cpu_seconds() -> float:
    """CPU time (s) of this process and its finished children (the gmsh processes)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def bench_one(path: Path, scheme: str, config: MeshConfig | None = None) -> dict:
    t0 = time.perf_counter()
    c0 = cpu_seconds()
    with PeakMemory() as mem:
        labels = read_label_map(path)
        t_read = time.perf_counter() - t0
        try:
            m = build_model(labels, scheme=PRESETS[scheme], config=config or MeshConfig())
        except RegtrackError as exc:
            return {"file": str(path), "error": str(exc), "seconds": time.perf_counter() - t0,
                    "cpu_seconds": cpu_seconds() - c0, "peak_gb": mem.peak / 1e9}
    q = m.meta["quality"]
    prep = m.meta["preparation"]
    return {
        "file": str(path), "side": prep["side"], "nodes": m.n_nodes, "tets": m.n_tets,
        "tumours_kept": len(prep["tumours_kept"]), "tumours_removed": len(prep["tumours_removed"]),
        "min_dihedral_deg": q["min_dihedral_deg"], "gamma_min": q["gamma_min"], "gamma_p5": q["gamma_p5"],
        "volume_error_pct": 100 * q["volume_error"],
        "tumour_volume_error_pct": [round(100 * t["volume_error"], 2) for t in q["tumours"]],
        "tumour_ml": [round(t["voxel_volume_mm3"] / 1000, 2) for t in q["tumours"]],
        "surface_distance_mm": q["surface_distance_mean_mm"], "attempts": len(m.meta["attempts"]),
        "seconds_read": t_read, "seconds": time.perf_counter() - t0, "cpu_seconds": cpu_seconds() - c0,
        "stages": m.meta.get("seconds_stages", {}), "peak_gb": mem.peak / 1e9,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exams", nargs="*", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows = []
    exams = args.exams or sorted(p.name.split("_")[1] for p in PELICANO.glob("Exam_*"))
    for e in exams:
        f = [p for p in glob.glob(str(PELICANO / f"Exam_{e}" / "*")) if "simple" in p.lower()]
        if not f:
            continue
        r = bench_one(Path(f[0]), "pelicano-simple")
        r["exam"] = e
        rows.append(r)
        print(json.dumps(r), flush=True)
    print("\n| exam | side | nodes | tets | tumours kept/removed | min dihedral (deg) | gamma min | gamma p5 | volume err % | tumour vol err % (ml) | mean surf dist (mm) | attempts | time (s) | CPU (s) | peak mem (GB) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['exam']} | failed: {r['error'][:120]} | | | | | | | | | | | {r['seconds']:.0f} | {r['cpu_seconds']:.0f} | {r['peak_gb']:.2f} |")
            continue
        tv = ", ".join(f"{e} ({v})" for e, v in zip(r["tumour_volume_error_pct"], r["tumour_ml"]))
        print(f"| {r['exam']} | {r['side']} | {r['nodes']} | {r['tets']} | {r['tumours_kept']}/{r['tumours_removed']} | "
              f"{r['min_dihedral_deg']:.2f} | {r['gamma_min']:.3f} | {r['gamma_p5']:.3f} | {r['volume_error_pct']:.2f} | {tv} | "
              f"{r['surface_distance_mm']:.2f} | {r['attempts']} | {r['seconds']:.0f} | {r['cpu_seconds']:.0f} | {r['peak_gb']:.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
