"""``regtrack surrogate build CASE``: a per-patient surrogate of one view's compression.

Simulates a Latin-hypercube design over c1, nu and D (and friction when given) on the
case's model (the mesh and every simulation go through the stage cache), fits the
surrogate (:mod:`regtrack.surrogate`), validates it on held-out simulations and writes
``DIR/surrogate.npz``, ``DIR/surrogate.json`` and ``DIR/validation.json``.
"""

from __future__ import annotations

import argparse
import logging

HELP = "per-patient surrogate of a view's compression: parameters -> nodal displacement"

log = logging.getLogger("regtrack.surrogate")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="simulate a design, fit and validate a surrogate",
                       description="simulate a design, fit and validate a surrogate")
    b.add_argument("case", help="case folder (holding case.toml)")
    b.add_argument("--view", type=str.upper, default="CC", choices=["CC", "MLO"],
                   help="mammographic view to simulate")
    b.add_argument("--points", type=int, default=12, help="training simulations (default 12)")
    b.add_argument("--holdout", type=int, default=4,
                   help="further simulations the surrogate is validated on (default 4)")
    b.add_argument("--c1", nargs=2, type=float, metavar=("LO", "HI"),
                   help="tissue c1 range in kPa (default 0.5x to 2x the case's c1)")
    b.add_argument("--nu", nargs=2, type=float, metavar=("LO", "HI"), default=[0.45, 0.49],
                   help="Poisson's ratio range (default 0.45 0.49)")
    b.add_argument("--d-range", nargs=2, type=float, metavar=("LO", "HI"), default=[0.25, 0.45],
                   help="compression degree D range (fraction of thickness; default 0.25 0.45)")
    b.add_argument("--friction", nargs=2, type=float, metavar=("LO", "HI"),
                   help="also vary the skin-plate friction in this range")
    b.add_argument("--regressor", default="gp", choices=["gp", "trees"],
                   help="coefficient regression: Gaussian process with a linear trend "
                   "(default; smaller leave-one-out error on the phantom) or extra trees")
    b.add_argument("--seed", type=int, default=0, help="seed of the design (default 0)")
    b.add_argument("--out", required=True, help="output folder")
    b.add_argument("--cache", help="stage cache (default .regtrack-cache, as `regtrack run`)")


def _check_range(pair, option: str, *, gt: float | None = None, ge: float | None = None,
                 lt: float | None = None) -> None:
    from regtrack.errors import ConfigError

    lo, hi = pair
    if not lo < hi:
        raise ConfigError(f"surrogate build {option} {lo:g} {hi:g}: LO must be below HI")
    if gt is not None and not lo > gt:
        raise ConfigError(f"surrogate build {option} {lo:g} {hi:g}: LO must be > {gt:g}")
    if ge is not None and not lo >= ge:
        raise ConfigError(f"surrogate build {option} {lo:g} {hi:g}: LO must be >= {ge:g}")
    if lt is not None and not hi < lt:
        raise ConfigError(f"surrogate build {option} {lo:g} {hi:g}: HI must be < {lt:g}")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from regtrack import _io
    from regtrack.case import load_case
    from regtrack.cli._checks import number_in_range, writable_folder
    from regtrack.pipeline.cache import DEFAULT_CACHE
    from regtrack.surrogate.design import ParameterBox
    from regtrack.surrogate.training import build_surrogate

    out = writable_folder(args.out, "--out")
    writable_folder(args.cache, "--cache")
    number_in_range(args.points, "--points", ge=5, why="a linear trend in 3 parameters and "
                    "one residual need 5 simulations")
    number_in_range(args.holdout, "--holdout", ge=0)
    _check_range(args.nu, "--nu", ge=0.0, lt=0.5)
    _check_range(args.d_range, "--d-range", gt=0.0, lt=1.0)
    case = load_case(args.case)
    c1 = args.c1 or [0.5 * case.config("mechanics").tissue_c1_kpa,
                     2.0 * case.config("mechanics").tissue_c1_kpa]
    _check_range(c1, "--c1", gt=0.0)
    names, lo, hi = ["c1", "nu", "target_D"], [c1[0], args.nu[0], args.d_range[0]], \
        [c1[1], args.nu[1], args.d_range[1]]
    if args.friction:
        _check_range(args.friction, "--friction", ge=0.0)
        names.append("friction")
        lo.append(args.friction[0])
        hi.append(args.friction[1])
    box = ParameterBox(tuple(names), tuple(lo), tuple(hi))
    total = args.points + args.holdout
    with _Bar(total) as say:
        sur, report = build_surrogate(case, args.view, box=box, n_points=args.points,
                                      n_holdout=args.holdout, seed=args.seed,
                                      regressor=args.regressor, say=say,
                                      cache_dir=Path(args.cache) if args.cache else DEFAULT_CACHE)
    assert out is not None
    sur.save(out)
    _io.write_json(out / "validation.json", report)
    log.info("surrogate of %s %s: %d simulations, %d PCA modes, fit %.2f s, predict %.4f s",
             case.id, args.view, report["n_train"], report["n_modes"], report["fit_s"],
             report["predict_s"])
    ho = report.get("held_out")
    if ho:
        log.info("held-out error over %d simulations: median %.3f mm, p95 %.3f mm, max %.3f mm",
                 len(ho["points"]), ho["pooled"]["median_mm"], ho["pooled"]["p95_mm"],
                 ho["pooled"]["max_mm"])
    log.info("wrote %s", out)
    return 0


class _Bar:
    """A rich progress bar over the simulations; each ``say("simulation i/n: ...")`` advances it."""

    def __init__(self, total: int) -> None:
        self.total = total

    def __enter__(self):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._p = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                           TimeElapsedColumn(), transient=True)
        self._p.__enter__()
        self._task = self._p.add_task("simulations", total=self.total)
        self._started = 0

        def say(msg: str) -> None:
            log.info(msg)
            if msg.startswith("simulation "):
                self._p.update(self._task, completed=self._started, description=msg[:70])
                self._started += 1

        return say

    def __exit__(self, *exc) -> None:
        self._p.__exit__(*exc)
