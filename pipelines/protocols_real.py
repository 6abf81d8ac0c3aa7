"""The shipped CC and MLO protocols on real-geometry models: the issue-5 table.

Usage::

    .venv/bin/python pipelines/protocols_real.py MODEL.vtu [MODEL.vtu ...] [--views cc mlo]
        [--contact friction=0.1 ...] [--solver force_tol=1e-4 ...] [--out DIR]

Models come from ``regtrack mesh`` (e.g. the Pelicano exams of ../shared/data/pelicano,
Pelicano et al., Sensors 2021 / PLoS One 2024, or sample_cases/phantom01).  Each run uses
the protocol defaults (friction 0.1, D = 38 % CC / 28 % MLO) and prints one markdown row:
case, nodes, view, D reached, plate forces (N), largest penetration (mm), the deepest node
behind the chest-wall plane at the end of a step (mm; ``behind_chest_wall_mm``), increments,
Newton iterations, multiplier updates, cut-backs, the Hessians made positive definite
(``inertia_corrections``), the largest relative force imbalance of the steps, and wall and
CPU seconds.  A failed run prints its error instead.
CPU time is the process time (on a shared machine the wall-clock depends on the other
jobs).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.config import config_from_assignments
from regtrack.errors import ConfigError
from regtrack.mechanics.contact import ContactConfig
from regtrack.mechanics.protocol import shipped_protocol
from regtrack.mechanics.run_view import (run_protocol_on_model, summarise,
                                         write_outputs)
from regtrack.model.io import load_model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--views", nargs="+", default=["cc", "mlo"])
    ap.add_argument("--contact", nargs="*", default=[], help="ContactConfig overrides key=value")
    ap.add_argument("--solver", nargs="*", default=[],
                    help="[mechanics.solver] overrides key=value")
    ap.add_argument("--out", type=Path, default=None, help="also write the result files here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    try:
        contact = config_from_assignments(ContactConfig, args.contact, where="--contact")
        mechanics = MechanicsConfig(solver=config_from_assignments(SolverOptions, args.solver,
                                                                   where="--solver"))
    except ConfigError as exc:
        ap.error(str(exc))
    print("| case | nodes | view | D | upper N | lower N | pen. mm | behind mm | incr. | iter. "
          "| aug. | cut | corr. | balance | wall s | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in args.models:
        model = load_model(path)
        for view in args.views:
            t, c = time.perf_counter(), time.process_time()
            try:
                res, timing = run_protocol_on_model(model, shipped_protocol(view),
                                                    mechanics=mechanics, contact=contact)
            except Exception as err:  # noqa: BLE001 - a table row per failure
                print(f"| {path.stem} | {model.n_nodes} | {view} | failed: {str(err)[:160]} |")
                continue
            sm = summarise(res, timing)
            aug = sum(s.solver.get("augmentations", 0) for s in res.steps)
            corr = sum(s.solver.get("inertia_corrections", 0) for s in res.steps)
            balance = sm["force_imbalance_rel"]
            print(f"| {path.stem} | {model.n_nodes} | {view} | {sm['D']:.3f} "
                  f"| {sm['upper_force_N']:.2f} | {sm['lower_force_N']:.2f} "
                  f"| {sm['max_penetration_mm']:.4f} | {_mm(sm['behind_chest_wall_mm'])} "
                  f"| {sm['increments']} | {sm['iterations']} "
                  f"| {aug} | {sm['cutbacks']} | {corr} "
                  f"| {'-' if balance is None else f'{balance:.1e}'} "
                  f"| {time.perf_counter() - t:.0f} | {time.process_time() - c:.0f} |", flush=True)
            if args.out:
                write_outputs(res, model, args.out, stem=f"{path.stem}_{view}")


def _mm(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


if __name__ == "__main__":
    main()
