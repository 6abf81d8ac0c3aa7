"""Runs of a study: :class:`RunSpec`, the runner interface and the worker-side wrapper.

A *runner* is a picklable, importable callable ``runner(spec: RunSpec) -> list[dict]``
that returns one flat metrics row per view.  The default, :func:`pipeline_runner` (name
``"pipeline"``), calls :func:`regtrack.pipeline.run.run_case`.

A study TOML names its runner by *name* only: a data file never chooses code to import.
The names come from a registry (:func:`known_runners`): the built-in ones, the Python entry
points of the group ``regtrack.study_runners`` declared by installed packages (in a
package's ``pyproject.toml``: ``[project.entry-points."regtrack.study_runners"]
mine = "mypkg.runners:mine"``), and those registered in-process by
:func:`register_runner` (tests).  The engine resolves the name in the parent process and
hands the function itself to the workers (pickled by reference, so its module must be
importable there).

:func:`execute` is what a worker process actually calls: it never raises for a failing
run but returns an outcome dict, so a bad case or a diverging simulation becomes a
failure *record* and the study goes on.  Only the death of the worker process itself
escapes (and is retried by the engine).  This module imports nothing heavy at the top,
so a worker sets its thread limits before numpy is loaded.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: Outcome status values.
OK, FAILED = "ok", "failed"


@dataclass(frozen=True)
class RunSpec:
    """Everything one run needs; picklable, paths as strings.

    Attributes
    ----------
    case_dir : str
        Absolute case folder.
    case_id : str
        Case id used in the table.
    overrides : dict
        TOML-like override sections (``{"mechanics": {"tissue_c1_kpa": 1.0}, ...}``).
    views : tuple of str
        Views to simulate and register (``"CC"``, ``"MLO"``).
    cache_dir : str
        Stage-cache root shared by every run (meshes and simulations are re-used).
    run_key : str
        Fingerprint of the run's inputs (runner, case content, overrides, views).
    params : dict
        The study parameter point (name -> value), copied into the table.
    out_dir : str or None
        Folder for the run's own files (overlays, JSON), or None to keep none.
    index : int
        Position in the study (table order).
    groups : tuple of str
        Share groups (mesh, simulation): the engine starts one run of a group first so
        the work they share is done once and found in the stage cache by the others.
    """

    case_dir: str
    case_id: str
    overrides: dict
    views: tuple[str, ...]
    cache_dir: str
    run_key: str
    params: dict = field(default_factory=dict)
    out_dir: str | None = None
    index: int = 0
    groups: tuple[str, ...] = ()


def pipeline_runner(spec: RunSpec) -> list[dict]:
    """The real pipeline: :func:`regtrack.pipeline.run.run_case` on the run's case."""
    from regtrack.pipeline.run import run_case

    return run_case(Path(spec.case_dir), overrides=spec.overrides, views=spec.views,
                    cache_dir=Path(spec.cache_dir),
                    out_dir=Path(spec.out_dir) if spec.out_dir else None, concurrent=False)


#: Entry-point group through which installed packages add study runners.
ENTRY_POINT_GROUP = "regtrack.study_runners"
#: Built-in runners (name -> the function).
BUILTIN_RUNNERS: dict[str, Callable[[RunSpec], list[dict]]] = {"pipeline": pipeline_runner}
_REGISTERED: dict[str, Callable[[RunSpec], list[dict]]] = {}


def register_runner(name: str, fn: Callable[[RunSpec], list[dict]]) -> None:
    """Make ``fn`` available as runner ``name`` in this process (tests, embedding code).

    ``fn`` must be a module-level function so the workers can unpickle it by reference.
    """
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"runner name {name!r}: use letters, digits, '-' and '_'")
    if not callable(fn):
        raise ValueError(f"runner {name!r}: {fn!r} is not callable")
    _REGISTERED[name] = fn


def _entry_points() -> dict[str, Any]:
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def known_runners() -> list[str]:
    """Names a study may give as ``runner`` (built-in, entry points, registered)."""
    return sorted({*BUILTIN_RUNNERS, *_entry_points(), *_REGISTERED})


def resolve_runner(name: str) -> Callable[[RunSpec], list[dict]]:
    """The runner function registered under ``name``.

    Raises
    ------
    regtrack.errors.ConfigError
        ``name`` is not a registered runner (the message lists the known ones), or its
        entry point cannot be loaded.
    """
    from regtrack.errors import ConfigError

    if name in _REGISTERED:
        return _REGISTERED[name]
    if name in BUILTIN_RUNNERS:
        return BUILTIN_RUNNERS[name]
    eps = _entry_points()
    if name not in eps:
        raise ConfigError(unknown_runner_message(name))
    try:
        fn = eps[name].load()
    except Exception as exc:  # noqa: BLE001 - a broken plug-in is a configuration problem
        raise ConfigError(f"runner = {name!r}: its entry point {eps[name].value!r} "
                          f"(group {ENTRY_POINT_GROUP}) cannot be loaded ({exc}); reinstall "
                          "the package that declares it") from None
    if not callable(fn):
        raise ConfigError(f"runner = {name!r}: entry point {eps[name].value!r} is not callable")
    return fn


def unknown_runner_message(name: str) -> str:
    """``runner = 'x': unknown runner; known runners: pipeline, ...`` (one line)."""
    from regtrack.config import closest_key

    known = known_runners()
    near = closest_key(name, known) if isinstance(name, str) else None
    hint = f" (did you mean {near!r}?)" if near else ""
    if isinstance(name, str) and ":" in name:
        hint += "; import paths are no longer accepted, name a registered runner"
    return (f"runner = {name!r}: unknown runner{hint}; known runners: {', '.join(known)} "
            f"(packages add runners through the {ENTRY_POINT_GROUP!r} entry points)")


def _clean(value: Any) -> Any:
    """JSON-safe scalar: numpy scalars -> Python, NaN/inf -> None."""
    if hasattr(value, "item") and not isinstance(value, (list, dict, str)):
        try:
            value = value.item()
        except (ValueError, AttributeError):
            pass
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def check_rows(rows: Any, spec: RunSpec) -> list[dict]:
    """Validate a runner's rows: a list with one flat dict per view of the run.

    Raises
    ------
    regtrack.errors.ResultCheckError
        Not a list of dicts, or the views do not match ``spec.views``.
    """
    from regtrack.errors import ResultCheckError

    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise ResultCheckError(f"runner for case '{spec.case_id}': returned "
                               f"{type(rows).__name__}, expected a list of dict rows (one per view)")
    views = [r.get("view") for r in rows]
    if sorted(map(str, views)) != sorted(spec.views):
        raise ResultCheckError(f"runner for case '{spec.case_id}': rows for views {views}, "
                               f"expected one row per view of {list(spec.views)}")
    return [{str(k): _clean(v) for k, v in r.items()} for r in rows]


def execute(runner: Callable[[RunSpec], list[dict]], spec: RunSpec) -> dict:
    """Run ``spec`` with the runner function ``runner`` (resolved by the engine from its
    registered name); return an outcome dict, never raise.

    The outcome has ``run_key``, ``status`` (``"ok"``/``"failed"``), ``rows``, ``error``
    (one line), ``error_type``, ``deterministic`` (True for a :class:`RegtrackError`,
    which the same inputs would raise again, so it is cached; other exceptions are
    re-attempted by the next study run), ``traceback``, ``seconds``, ``host`` and ``pid``.
    """
    from regtrack.errors import RegtrackError

    t0 = time.perf_counter()
    base = {"run_key": spec.run_key, "host": socket.gethostname(), "pid": os.getpid()}
    try:
        rows = check_rows(runner(spec), spec)
    except Exception as exc:  # noqa: BLE001 - every failure becomes a record
        msg = " ".join(str(exc).split()) or type(exc).__name__
        log.debug("run %s of case %s failed: %s", spec.run_key, spec.case_id, msg)
        return {**base, "status": FAILED, "rows": [], "error": msg,
                "error_type": type(exc).__name__,
                "deterministic": isinstance(exc, RegtrackError),
                "traceback": traceback.format_exc(limit=20),
                "seconds": time.perf_counter() - t0}
    return {**base, "status": OK, "rows": rows, "error": None, "error_type": None,
            "deterministic": True, "traceback": None, "seconds": time.perf_counter() - t0}


def make_run(case: Any, digest: str, point: dict, *, base: dict, views: tuple[str, ...],
             runner: str, cache_dir: Path, out_root: Path | None = None, index: int = 0) -> RunSpec:
    """The run of one case (a :class:`~regtrack.study.spec.CaseRef`) at one parameter point.

    Its key is the fingerprint of the runner, the case id and folder content (``digest``),
    the overrides and the views, so an edited case or a changed parameter gives a new key.
    """
    from regtrack.pipeline.cache import fingerprint
    from regtrack.study.params import apply_point

    ov = apply_point(base, point, views=views)
    key = fingerprint("study-run", runner, case.case_id, digest, ov, list(views))
    mesh_group = fingerprint("mesh", digest, ov.get("model", {}))
    sim_group = fingerprint("sim", digest, {k: v for k, v in ov.items() if k != "registration"},
                            list(views))
    return RunSpec(case_dir=str(case.case_dir), case_id=case.case_id, overrides=ov,
                   views=tuple(views), cache_dir=str(cache_dir), run_key=key, params=dict(point),
                   out_dir=str(out_root / case.case_id / key) if out_root else None, index=index,
                   groups=(mesh_group, sim_group))


def make_runs(study: Any) -> list[RunSpec]:
    """Expand a :class:`regtrack.study.spec.Study` into its runs (case-major order)."""
    from regtrack.pipeline.cache import file_digest

    points = study.points()
    out_root = study.out_dir / "runs" if "run_files" in study.outputs else None
    runs: list[RunSpec] = []
    for case in study.cases:
        digest = file_digest(case.case_dir)
        for point in points:
            runs.append(make_run(case, digest, point, base=study.overrides, views=study.views,
                                 runner=study.runner, cache_dir=study.cache_dir,
                                 out_root=out_root, index=len(runs)))
    return runs
