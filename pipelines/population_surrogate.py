"""Leave-one-patient-out (LOPO) evaluation of the population surrogate (issue 56, item 2).

For each view, each exam of the cohort is left out in turn (both breasts of an exam
together); a tree ensemble (:mod:`regtrack.surrogate.population`) is fitted on the other
exams' simulated compressions and predicts the left-out breasts' displacement fields from
their reference meshes alone; the mean-shape baseline is evaluated on the same folds.
Per left-out breast: median / p95 / max nodal error (mm, Euclidean distance between the
predicted and simulated deformed positions) of the ensemble and the baseline, the fit and
prediction seconds.  Writes ``lopo.csv``, ``lopo.md`` and ``importances.csv`` to ``--out``.

Usage::

    .venv/bin/python pipelines/population_surrogate.py --runs COHORT/runs \\
        --views cc mlo --out reports/population_surrogate

``COHORT`` is the ``--out`` folder of ``pipelines/bench_cohort.py`` run at the defaults.
Expects ``<runs>/<breast>/out/model.vtu`` and ``<runs>/<breast>/sim_default_<view>/*.vtu``
(the result files of ``regtrack simulate``); breasts without a result for a view are skipped
for that view.  Reads only; does not simulate.

Measured on the 27 breasts of 24 exams (``--jobs 2``, defaults otherwise), medians over the
left-out breasts of their median / p95 nodal error: CC 3.11 / 7.61 mm (mean-shape baseline
4.12 / 8.77), MLO 3.47 / 8.03 mm (baseline 12.20 / 32.17); docs/performance.md has the table.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from regtrack.model.io import load_model
from regtrack.surrogate.population import (FEATURES, REGRESSORS, PopulationSurrogate,
                                           lopo_folds, mean_shape_baseline, node_features,
                                           nodal_error_summary)
from regtrack.virtual.io import read_result_positions

MARTINEZ_MEDIAN_MM = 0.62  # Martínez-Martínez et al. 2017, within one patient's deformations


def load_view(runs: Path, view: str, sim: str) -> list[dict]:
    """Breasts with a complete result for ``view``: name, model, features, displacement (mm)."""
    out = []
    for d in sorted(p for p in runs.iterdir() if (p / "out" / "model.vtu").is_file()):
        res = sorted((d / f"{sim}_{view}").glob("*.vtu"))
        if not res:
            print(f"  {d.name}: no {sim}_{view} result, skipped", flush=True)
            continue
        side = res[0].with_suffix(".json")
        if side.is_file():
            doc = json.JSONDecoder().raw_decode(side.read_text())[0]
            if not doc.get("summary", {}).get("complete", True):
                print(f"  {d.name}: {view} result incomplete, skipped", flush=True)
                continue
        model = load_model(d / "out" / "model.vtu")
        u = read_result_positions(res[0], model) - model.points
        out.append({"name": d.name, "model": model, "nf": node_features(model, view), "u": u})
    return out


def run_view(breasts: list[dict], view: str, args, errs: dict) -> list[dict]:
    """LOPO folds of one view; appends each left-out breast's nodal errors (mm) to ``errs``."""
    rows = []
    names = [b["name"] for b in breasts]
    folds = lopo_folds(names)
    if args.exams:
        folds = [f for f in folds if f[0] in args.exams]
    for k, (exam, train, test) in enumerate(folds):
        t0 = time.perf_counter()
        sur = PopulationSurrogate(view.upper(), kind=args.regressor, per_patient=args.per_patient,
                                  regressor_options={"n_estimators": args.trees,
                                                     "min_samples_leaf": args.min_leaf,
                                                     "max_features": args.max_features,
                                                     "n_jobs": args.jobs})
        sur.fit([breasts[i]["nf"] for i in train], [breasts[i]["u"] for i in train])
        for i in test:
            b = breasts[i]
            pred = sur.predict(b["model"])          # features recomputed: timed end to end
            base = mean_shape_baseline([breasts[j]["nf"] for j in train],
                                       [breasts[j]["u"] for j in train], b["nf"])
            es, eb = nodal_error_summary(pred, b["u"]), nodal_error_summary(base, b["u"])
            row = {"view": view.upper(), "breast": b["name"], "exam": exam,
                   "side": b["model"].frame.side, "nodes": b["model"].n_nodes,
                   "T0_mm": round(b["nf"].T0, 1),
                   "median_disp_mm": float(np.median(np.linalg.norm(b["u"], axis=1))),
                   **{f"ens_{m}": v for m, v in es.items()},
                   **{f"base_{m}": v for m, v in eb.items()},
                   "fit_s": sur.fit_s, "fit_cpu_s": sur.fit_cpu_s, "features_s": sur.features_s,
                   "predict_s": sur.predict_s, "predict_cpu_s": sur.predict_cpu_s}
            errs.setdefault(view.upper(), {"ens": [], "base": []})
            errs[view.upper()]["ens"].append(np.linalg.norm(pred - b["u"], axis=1))
            errs[view.upper()]["base"].append(np.linalg.norm(base - b["u"], axis=1))
            rows.append(row)
            print(f"  [{view} {k + 1}/{len(folds)}] {b['name']}: ensemble median/p95/max "
                  f"{es['median_mm']:.2f}/{es['p95_mm']:.2f}/{es['max_mm']:.2f} mm, baseline "
                  f"{eb['median_mm']:.2f}/{eb['p95_mm']:.2f}/{eb['max_mm']:.2f} mm "
                  f"(fit {sur.fit_s:.1f} s, features {sur.features_s * 1e3:.0f} ms, "
                  f"predict {sur.predict_s * 1e3:.0f} ms, "
                  f"fold {time.perf_counter() - t0:.1f} s)", flush=True)
    return rows


def summary_lines(rows: list[dict], view: str, errs: dict) -> list[str]:
    r = [x for x in rows if x["view"] == view]
    if not r:
        return []
    pooled = {k: np.concatenate(v) for k, v in errs[view].items()}
    med = lambda key: float(np.median([x[key] for x in r]))  # noqa: E731
    worst = max(r, key=lambda x: x["ens_median_mm"])
    return [f"| {view} | {len(r)} | {med('ens_median_mm'):.2f} | {med('ens_p95_mm'):.2f} | "
            f"{med('base_median_mm'):.2f} | {med('base_p95_mm'):.2f} | "
            f"{worst['breast']} ({worst['ens_median_mm']:.2f} / {worst['ens_p95_mm']:.2f}) | "
            f"{np.median(pooled['ens']):.2f} / {np.percentile(pooled['ens'], 95):.2f} | "
            f"{np.median(pooled['base']):.2f} / {np.percentile(pooled['base'], 95):.2f} | "
            f"{med('fit_s'):.1f} s ({med('fit_cpu_s'):.1f} s CPU) | {med('features_s') * 1e3:.0f} + "
            f"{med('predict_s') * 1e3:.0f} ms ({med('predict_cpu_s') * 1e3:.0f} ms CPU) | "
            f"{med('median_disp_mm'):.1f} |"]


def write(rows: list[dict], imps: dict, errs: dict, out: Path, args) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "lopo.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    with open(out / "importances.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["view", *FEATURES])
        for v, d in imps.items():
            w.writerow([v, *(f"{d.get(n, 0.0):.4f}" for n in FEATURES)])
    md = [f"# Population surrogate, leave-one-patient-out ({args.regressor}, {args.trees} trees, "
          f"min leaf {args.min_leaf}, max features {args.max_features}, "
          f"{args.per_patient} nodes per training breast)", "",
          "Nodal error = distance (mm) between predicted and simulated deformed positions; "
          "medians over the left-out breasts of each breast's median / p95; 'all nodes' pools "
          "the nodes of every left-out breast.  Predict = features + ensemble, one breast; wall "
          "seconds on a shared host, the process's CPU seconds in brackets.  "
          f"Martínez-Martínez et al. 2017: {MARTINEZ_MEDIAN_MM} mm median within one patient.", "",
          "| view | breasts | ensemble median | ensemble p95 | baseline median | baseline p95 | "
          "worst breast (median / p95) | all nodes ensemble median / p95 | all nodes baseline "
          "median / p95 | fit | predict | median displacement |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v in dict.fromkeys(r["view"] for r in rows):
        md += summary_lines(rows, v, errs)
    md += ["", "| view | breast | nodes | T0 mm | displacement median | ensemble median / p95 / max | "
           "baseline median / p95 / max | fit s | predict ms |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['view']} | {r['breast']} | {r['nodes']} | {r['T0_mm']} | "
                  f"{r['median_disp_mm']:.1f} | {r['ens_median_mm']:.2f} / {r['ens_p95_mm']:.2f} / "
                  f"{r['ens_max_mm']:.1f} | {r['base_median_mm']:.2f} / {r['base_p95_mm']:.2f} / "
                  f"{r['base_max_mm']:.1f} | {r['fit_s']:.1f} | "
                  f"{(r['features_s'] + r['predict_s']) * 1e3:.0f} |")
    (out / "lopo.md").write_text("\n".join(md) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, required=True,
                    help="the runs/ folder of a pipelines/bench_cohort.py output at the defaults")
    ap.add_argument("--views", nargs="+", default=["cc", "mlo"], choices=["cc", "mlo"])
    ap.add_argument("--sim", default="sim_default", help="result folder prefix (<sim>_<view>)")
    ap.add_argument("--out", type=Path, default=Path("reports/population_surrogate"))
    ap.add_argument("--regressor", default="extra", choices=REGRESSORS)
    ap.add_argument("--trees", type=int, default=40)
    ap.add_argument("--min-leaf", type=int, default=3)
    ap.add_argument("--max-features", type=float, default=1.0)
    ap.add_argument("--per-patient", type=int, default=1500,
                    help="training nodes drawn per breast (seeded)")
    ap.add_argument("--jobs", type=int, default=1, help="scikit-learn n_jobs (the host has 2 cores)")
    ap.add_argument("--exams", nargs="*", help="only these folds (exam keys, e.g. exam02)")
    args = ap.parse_args(argv)

    rows, imps, errs = [], {}, {}
    for view in args.views:
        t = time.perf_counter()
        print(f"{view.upper()}: loading {args.runs}", flush=True)
        breasts = load_view(args.runs, view, args.sim)
        print(f"{view.upper()}: {len(breasts)} breasts loaded in {time.perf_counter() - t:.1f} s",
              flush=True)
        rows += run_view(breasts, view, args, errs)
        full = PopulationSurrogate(view.upper(), kind=args.regressor, per_patient=args.per_patient,
                                   regressor_options={"n_estimators": args.trees,
                                                      "min_samples_leaf": args.min_leaf,
                                                      "max_features": args.max_features,
                                                      "n_jobs": args.jobs})
        imps[view.upper()] = full.fit([b["nf"] for b in breasts], [b["u"] for b in breasts]).importances()
    if not rows:
        print("no results", file=sys.stderr)
        return 1
    write(rows, imps, errs, args.out, args)
    print((args.out / "lopo.md").read_text().split("\n\n| view | breast |")[0])
    print(f"wrote {args.out}/lopo.csv, lopo.md, importances.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
