"""``regtrack calibrate CASE``: find c1 and nu (and optionally friction) for a case."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

HELP = "calibrate c1 / nu (/ friction) of a case: coarse grid + bounded optimiser, cached runs"

log = logging.getLogger("regtrack.calibrate")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case", help="case folder (holding case.toml)")
    parser.add_argument("--c1", nargs=2, type=float, metavar=("LO", "HI"), default=[0.2, 3.0],
                        help="tissue c1 range in kPa (default 0.2 3.0, geometric grid)")
    parser.add_argument("--nu", nargs=2, type=float, metavar=("LO", "HI"), default=[0.45, 0.49],
                        help="Poisson's ratio range (default 0.45 0.49, as the paper's Figure 8)")
    parser.add_argument("--friction", nargs=2, type=float, metavar=("LO", "HI"),
                        help="also calibrate the skin-plate friction in this range")
    parser.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                        help="hold a parameter fixed instead (e.g. --fix nu=0.49); repeatable")
    parser.add_argument("--views", nargs="+", default=["CC"], choices=["CC", "MLO"])
    parser.add_argument("--d-range", nargs=2, type=float, default=[0.2, 0.6],
                        metavar=("LO", "HI"), help="clinical range of the compression degree D "
                        "(fraction of breast thickness; default 0.2 0.6)")
    parser.add_argument("--objective", default="mean", choices=["mean", "BS_Av", "TS_Av"],
                        help="maximise (BS_Av + TS_Av)/2 (mean) or one indicator")
    parser.add_argument("--grid", type=int, default=4, help="grid values per parameter (>= 2)")
    parser.add_argument("--max-evals", type=int, default=40, help="most optimiser runs")
    parser.add_argument("--out", help="output folder (default <case>_calibration beside the case)")
    parser.add_argument("--cache", help="cache folder (default <out>/cache; share it with "
                        "studies of the same case to re-use their runs)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address")
    parser.add_argument("--workers", type=int, default=0, help="local workers (0 = machine)")
    parser.add_argument("--runner", help="name of a registered runner (default: pipeline; "
                        "packages add runners through the 'regtrack.study_runners' entry "
                        "points)")
    parser.add_argument("--surrogate", nargs="+", metavar="DIR",
                        help="surrogate folders (`regtrack surrogate build`, one per view): a "
                        "global search on them replaces the grid; every reported number is "
                        "still from a full run")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from regtrack import _io
    from regtrack.errors import ConfigError
    from regtrack.study import plots
    from regtrack.study.calibrate import calibrate, to_json
    from regtrack.study.spec import DEFAULT_RUNNER

    from regtrack.cli._checks import writable_folder

    writable_folder(args.out, "--out")
    writable_folder(args.cache, "--cache")
    if args.runner is not None:
        from regtrack.study.runner import known_runners, unknown_runner_message

        if args.runner not in known_runners():
            msg = unknown_runner_message(args.runner)
            raise ConfigError(msg.replace("runner = ", "--runner ", 1))
    fixed: dict[str, float | str] = {}
    for item in args.fix:
        name, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"calibrate --fix {item!r}: write NAME=VALUE, e.g. --fix nu=0.49")
        try:
            fixed[name.strip()] = float(value)
        except ValueError:
            raise ConfigError(f"calibrate --fix {item!r}: the value must be a number") from None
    bounds = {"c1": tuple(args.c1), "nu": tuple(args.nu)}
    if args.friction:
        bounds["friction"] = tuple(args.friction)
    for name in fixed:
        bounds.pop(name, None)
    surrogates = None
    if args.surrogate:
        from regtrack.surrogate import Surrogate

        surrogates = {}
        for folder in args.surrogate:
            sur = Surrogate.load(folder)
            view = str((sur.meta.get("validation") or {}).get("view", "")).upper()
            if view not in ("CC", "MLO") or view in surrogates:
                raise ConfigError(f"calibrate --surrogate {folder}: "
                                  + (f"a second surrogate of {view}; give one per view" if view in surrogates
                                     else "no view recorded; rebuild it with `regtrack surrogate build`"))
            surrogates[view] = sur
    case = Path(args.case)
    # outside the case folder: the run keys hash the case folder's content
    out = Path(args.out) if args.out else case.resolve().parent / f"{case.resolve().name}_calibration"
    cache = Path(args.cache) if args.cache else out / "cache"
    res = calibrate(case, bounds=bounds, fixed=fixed, views=tuple(args.views),
                    d_range=tuple(args.d_range), objective=args.objective, grid=args.grid,
                    max_evals=args.max_evals, runner=args.runner or DEFAULT_RUNNER,
                    cache_dir=cache, scheduler=args.scheduler, workers=args.workers,
                    progress=not args.no_progress, surrogates=surrogates)
    _io.write_json(out / "calibration.json", to_json(res))
    _io.save_figure(plots.calibration_figure(res), out / "calibration.png")
    opt = res.optimum
    log.info("optimum for %s: %s  S = %.2f %%  D = %s  (%s)", res.case_id,
             ", ".join(f"{k} = {v:g}" for k, v in opt.params.items()), opt.score,
             ", ".join(f"{r.get('view')}: {r.get('D'):.3f}" for r in opt.rows if r.get("D") is not None),
             "feasible" if res.feasible else f"D outside range by {opt.violation:.3f}")
    for name, s in res.sensitivity.items():
        spread = "" if math.isnan(s["grid_spread"]) else f", grid spread {s['grid_spread']:.2f} %"
        log.info("sensitivity %s: dS/d%s = %.3g %% per unit (%s)%s", name, name,
                 s["dS_dparam"], s["method"], spread)
    if res.surrogate is not None:
        su = res.surrogate
        log.info("surrogate search: %d evaluations, S %.2f %% predicted, %.2f %% simulated "
                 "at its optimum; uncertainty %s", su["evaluations"], su["score_surrogate"],
                 su["score_full"], ", ".join(f"{k} {lo:.4g} to {hi:.4g}"
                                              for k, (lo, hi) in su["interval"].items()))
    log.info("%d runs computed, %d cached; results in %s", res.computed, res.cached, out)
    return 0 if res.feasible else 5
