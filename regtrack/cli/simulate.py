"""``regtrack simulate``: run load steps on a model file, or a mammography view of a case.

File level (the contract of docs/design.md)::

    regtrack simulate --model M.vtu --config C.toml --out R.vtu

runs the ``[[steps]]`` of ``C.toml`` (gravity ramps, prescribed displacements of node
sets; see :mod:`regtrack.mechanics.steps`) with its ``[mechanics]`` overrides and writes
``R.vtu`` (displacement per step) and ``R.json`` (statistics, chest-wall reaction,
config).  Case level::

    regtrack simulate CASE --view cc|mlo|biopsy --model M.vtu --out DIR

runs the view's compression protocol (:func:`regtrack.mechanics.run_view.simulate_view`).
"""

from __future__ import annotations

import argparse
import logging
import time

LOGGER = "regtrack.simulate"
HELP = "simulate a model: load steps from a config file, or a CC/MLO/biopsy compression of a case"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case", nargs="?", help="case folder or case.toml (case-level form, with --view)")
    parser.add_argument("--model", required=True, help="model .vtu (from `regtrack mesh` or any tool "
                        "following the model contract)")
    parser.add_argument("--config", help="simulation config TOML ([mechanics] + [[steps]]); file-level form")
    parser.add_argument("--view", type=str.upper, choices=["CC", "MLO", "BIOPSY"],
                        help="mammographic view, or BIOPSY: the latero-medial compression of the "
                        "prone breast in an MR biopsy coil (case-level form)")
    parser.add_argument("--out", required=True, help="result .vtu (file level) or output folder (case level)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from regtrack.errors import ConfigError
    from regtrack.model.io import load_model

    from regtrack.cli._checks import existing_file, writable_folder

    log = logging.getLogger(LOGGER)
    existing_file(args.model, "--model", "model .vtu")
    out_path = Path(args.out)
    writable_folder(out_path.parent if out_path.suffix == ".vtu" else out_path, "--out")
    if args.case is not None or args.view is not None:
        if args.case is None or args.view is None:
            raise ConfigError("regtrack simulate: the case-level form needs both CASE and "
                              "--view cc|mlo|biopsy")
        from regtrack.case.loader import load_case
        from regtrack.mechanics.run_view import simulate_view

        case = load_case(args.case)
        model = load_model(args.model)
        with _progress() as progress:
            res = simulate_view(case, model, args.view, out_dir=Path(args.out), progress=progress)
        log.info("wrote %s", ", ".join(str(f) for f in getattr(res, "files", [])))
        return 0
    if not args.config:
        raise ConfigError("regtrack simulate: give --config C.toml (file-level form) or CASE "
                          "--view cc|mlo|biopsy")
    return _run_file_level(Path(args.model), Path(args.config), Path(args.out), log)


def _run_file_level(model_path, config_path, out, log) -> int:
    import tomllib

    import meshio

    from regtrack.config import to_table
    from regtrack.errors import ConfigError, InputFileError
    from regtrack.mechanics.io import save_result
    from regtrack.mechanics.problem import build_problem
    from regtrack.mechanics.steps import parse_simulation, run_steps
    from regtrack.model.io import load_model

    if not config_path.is_file():
        raise InputFileError(f"{config_path}: simulation config not found")
    try:
        doc = tomllib.loads(config_path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{config_path}: invalid TOML ({exc})") from exc
    mech, steps, warnings = parse_simulation(doc, where=str(config_path))
    for w in warnings:
        log.warning(w)
    if out.suffix != ".vtu":
        raise ConfigError(f"--out {out}: the file-level result must be a .vtu path")
    model = load_model(model_path)
    fields = {k: v for k, v in meshio.read(model_path).point_data.items() if k != "fixed"}
    problem = build_problem(model, mech)
    with _progress() as progress:
        deformation = run_steps(problem, steps, node_sets=fields, progress=progress, where=f"{config_path} [[steps]]")
    vtu, js = save_result(out, model, deformation, config={"mechanics": to_table(mech),
                                                           "steps": [s.__dict__ for s in steps]})
    log.info("wrote %s and %s; chest-wall reaction %s N", vtu, js, deformation.steps[-1].chest_wall_reaction_n)
    return 0


class _progress:
    """Rich progress bar over the steps' pseudo-time; yields a ``(step, t)`` callback.
    Without a terminal (a log file, a batch job), a plain log line now and then instead
    (:class:`regtrack.cli._console.IncrementLines`, with the seconds since the start)."""

    def __init__(self, clock=time.monotonic) -> None:
        self.clock = clock

    def __enter__(self):
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        from regtrack.cli._console import IncrementLines

        console = Console(stderr=True)
        self._p = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("t = {task.completed:.3f}"),
                           TimeElapsedColumn(), transient=True, console=console)
        self._p.__enter__()
        self._tasks: dict[str, int] = {}
        t0 = self.clock()
        lines = None if console.is_terminal else IncrementLines(
            lambda text: logging.getLogger(LOGGER).info("%s (%.0f s)", text, self.clock() - t0),
            clock=self.clock)

        def update(step: str, t: float, **info) -> None:
            if lines is not None:
                lines("", step or "step", t, info)
            if step not in self._tasks:
                self._tasks[step] = self._p.add_task(step or "step", total=1.0)
            if info.get("working_to") is not None:  # within an increment: the clock ticks
                return
            extra = "".join(f" · {k} {info[k]:{fmt}}" for k, fmt in (("D", ".3f"), ("force_N", ".1f"))
                            if isinstance(info.get(k), (int, float)))
            self._p.update(self._tasks[step], completed=t,
                           description=(step or "step") + extra.replace("force_N", "F (N)"))

        return update

    def __exit__(self, *exc):
        return self._p.__exit__(*exc)
