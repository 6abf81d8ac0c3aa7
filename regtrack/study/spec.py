"""Study definition (TOML): schema, validation and expansion into runs.

A study file looks like::

    [study]
    name = "figure8"
    views = ["CC"]                       # CC, MLO or both
    outputs = ["csv", "figure8", "d_T", "pdf"]
    # out = "results/figure8"            # default: <study file stem>_results beside it
    # cache = "..."                      # default: <out>/cache (shared by every run)
    # workers = 0                        # local pool size; 0 = sized to the machine
    # retries = 2                        # re-tries of a run whose worker died
    # combine = "product"                # or "zip" (lists of equal length)

    [cases]
    paths = ["../sample_cases/phantom01"]   # case folders, relative to this file
    glob = ["cohort/*"]                     # and/or glob patterns

    [parameters]                          # see regtrack.study.params for the names
    c1 = {start = 0.2, stop = 2.0, num = 7, scale = "log"}   # kPa
    nu = [0.45, 0.46, 0.47, 0.48, 0.49]

    [overrides.model]                     # fixed overrides applied to every run
    target_nodes = 3000

Every path is relative to the study file.  :func:`load_study` validates the whole file
(all problems at once, each naming the file and key) before anything is written.
"""

from __future__ import annotations

import glob as globmod
import itertools
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack.config import closest_key, param, parse_section
from regtrack.errors import ConfigError
from regtrack.study import params as P
from regtrack.views import VIEWS

#: Outputs a study can write.  ``parquet`` needs the optional ``pyarrow`` package.
OUTPUTS = ("csv", "parquet", "figure8", "d_T", "pdf", "run_files")
DEFAULT_OUTPUTS = ("csv", "figure8", "d_T", "pdf")
DEFAULT_RUNNER = "pipeline"
TOP_LEVEL = ("study", "cases", "parameters", "overrides")


@dataclass(frozen=True)
class StudyTable:
    """The ``[study]`` section."""

    name: str = param("study", "", "study name (used in titles and file names)")
    views: list[str] = param(None, "", "views simulated and registered in every run",
                             default_factory=lambda: ["CC"])
    outputs: list[str] = param(None, "", "outputs to write: " + ", ".join(OUTPUTS),
                               default_factory=lambda: list(DEFAULT_OUTPUTS))
    out: str | None = param(None, "", "output folder (relative to the study file)")
    cache: str | None = param(None, "", "cache folder shared by every run (default <out>/cache)")
    runner: str = param(DEFAULT_RUNNER, "", "name of a registered runner (built-in "
                        "'pipeline', or one declared in the 'regtrack.study_runners' entry "
                        "points)")
    workers: int = param(0, "-", "local worker processes; 0 = sized to the machine", ge=0, le=1024)
    retries: int = param(2, "-", "re-tries of a run whose worker process died", ge=0, le=20)
    memory_per_run_gb: float = param(2.0, "GB", "memory one run needs (caps the local pool size)",
                                     gt=0, le=1e4)
    combine: str = param("product", "", "how parameter lists combine",
                         choices=("product", "zip"))

    def check(self) -> list[str]:
        """Cross-field problems (views, outputs, runner), checked even when keys are bad."""
        out = []
        bad_views = [v for v in self.views if v not in VIEWS]
        if bad_views or not self.views or len(set(self.views)) != len(self.views):
            out.append(f"views = {self.views!r}: give distinct views among {', '.join(VIEWS)}")
        bad = [o for o in self.outputs if o not in OUTPUTS]
        if bad:
            out.append(f"outputs: unknown {', '.join(map(repr, bad))}; use {', '.join(OUTPUTS)}")
        from regtrack.study.runner import known_runners, unknown_runner_message

        if self.runner not in known_runners():
            out.append(unknown_runner_message(self.runner))
        return out


@dataclass(frozen=True)
class CaseRef:
    """One case of a study: its folder (absolute) and id (``[case] id`` or folder name)."""

    case_dir: Path
    case_id: str


@dataclass(frozen=True)
class Study:
    """A validated study.  ``parameters`` maps each varied name to its values, in order."""

    path: Path
    name: str
    cases: tuple[CaseRef, ...]
    parameters: dict[str, tuple]
    combine: str
    views: tuple[str, ...]
    outputs: tuple[str, ...]
    overrides: dict
    out_dir: Path
    cache_dir: Path
    runner: str
    workers: int
    retries: int
    memory_per_run_gb: float
    warnings: tuple[str, ...] = field(default=())

    def points(self) -> list[dict[str, Any]]:
        """Parameter points (dicts name -> value) in a stable order."""
        names = list(self.parameters)
        if not names:
            return [{}]
        lists = [self.parameters[n] for n in names]
        combos = zip(*lists) if self.combine == "zip" else itertools.product(*lists)
        return [dict(zip(names, c)) for c in combos]

    @property
    def n_runs(self) -> int:
        return len(self.cases) * len(self.points())


def _fail(problems: list[str]) -> ConfigError:
    if len(problems) == 1:
        return ConfigError(problems[0])
    return ConfigError(f"{len(problems)} problems:\n" + "\n".join(f"  - {p}" for p in problems))


def _values(name: str, spec: Any, *, where: str) -> tuple[list, list[str]]:
    """Raw values of one parameter from a scalar, a list or a grid table."""
    if isinstance(spec, dict):
        unknown = set(spec) - {"start", "stop", "num", "step", "scale"}
        if unknown:
            return [], [f"{where} {name}: unknown grid key(s) {sorted(unknown)}; use start, stop "
                        "and num or step, and optionally scale = 'linear' or 'log'"]
        try:
            start, stop = float(spec["start"]), float(spec["stop"])
        except (KeyError, TypeError, ValueError):
            return [], [f"{where} {name} = {spec!r}: a grid needs numbers start and stop"]
        scale = spec.get("scale", "linear")
        if scale not in ("linear", "log"):
            return [], [f"{where} {name}.scale = {scale!r}: must be 'linear' or 'log'"]
        if ("num" in spec) == ("step" in spec):
            return [], [f"{where} {name} = {spec!r}: give exactly one of num or step"]
        if scale == "log" and (start <= 0 or stop <= 0):
            return [], [f"{where} {name}: a log grid needs start and stop > 0"]
        if "num" in spec:
            num = spec["num"]
            if isinstance(num, bool) or not isinstance(num, int) or num < 1:
                return [], [f"{where} {name}.num = {num!r}: must be an integer >= 1"]
            vals = (np.geomspace if scale == "log" else np.linspace)(start, stop, num)
        else:
            step = spec["step"]
            if isinstance(step, bool) or not isinstance(step, (int, float)) or step <= 0 \
                    or scale == "log" or stop < start:
                return [], [f"{where} {name}.step = {step!r}: needs step > 0, stop >= start and a "
                             "linear scale"]
            vals = np.arange(start, stop + step * 1e-9, step)
        return [float(f"{v:.10g}") for v in vals], []
    vals = list(spec) if isinstance(spec, list) else [spec]
    if not vals:
        return [], [f"{where} {name} = []: give at least one value"]
    return vals, []


def _parse_parameters(table: Any, *, where: str) -> tuple[dict[str, tuple], list[str], list[str]]:
    if table is None:
        return {}, [], []
    if not isinstance(table, dict):
        return {}, [f"{where}: expected a table 'name = values'"], []
    out: dict[str, tuple] = {}
    problems: list[str] = []
    warnings: list[str] = []
    for name, spec in table.items():
        if isinstance(spec, dict) and P.split_dotted(name) is None and name not in P.ALIASES \
                and name in P.SECTIONS[:4]:
            # [parameters.registration] bracket_deg = [...] : nested form of dotted names
            for key, sub in spec.items():
                sub_out, p, w = _parse_parameters({f"{name}.{key}": sub}, where=where)
                out.update(sub_out)
                problems += p
                warnings += w
            continue
        raw, p = _values(name, spec, where=where)
        problems += p
        coerced = []
        for i, v in enumerate(raw):
            cv, pv, wv = P.check_value(name, v, where=where)
            problems += pv
            warnings += wv
            if pv:
                break
            coerced.append(cv)
        if len(set(map(repr, coerced))) != len(coerced):
            problems.append(f"{where} {name} = {raw!r}: duplicate values; list each value once")
        if not p:
            out[name] = tuple(coerced)
    return out, problems, warnings


def case_id_of(case_dir: Path) -> str:
    """``[case] id`` of a case folder's ``case.toml``, else the folder name; replaced by
    the pipeline's pseudonym (:func:`regtrack.privacy.pseudonymous_id`) when it contains a
    patient identifier of the case's DICOM files, so study and calibration outputs (tables,
    figure names, JSON) name the case as ``regtrack run`` does."""
    try:
        doc = tomllib.loads((case_dir / "case.toml").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return case_dir.name  # the runner reports the bad case.toml as a failed run
    cid = doc.get("case", {}).get("id") if isinstance(doc.get("case"), dict) else None
    cid = cid if isinstance(cid, str) and cid else case_dir.name
    from regtrack.privacy import identifiers_of_case_folder, pseudonymous_id

    return pseudonymous_id(cid, identifiers_of_case_folder(case_dir))


def _parse_cases(spec: Any, *, root: Path, where: str) -> tuple[list[CaseRef], list[str]]:
    if spec is None:
        return [], [f"{where}: missing; list the case folders, e.g. [cases] paths = ['case01']"]
    if isinstance(spec, list):
        spec = {"paths": spec}
    if not isinstance(spec, dict):
        return [], [f"{where}: expected a list of folders or a table with paths and/or glob"]
    problems = []
    unknown = set(spec) - {"paths", "glob"}
    for k in unknown:
        near = closest_key(k, ("paths", "glob"))
        problems.append(f"{where}: unknown key '{k}'" + (f" (did you mean '{near}'?)" if near else ""))
    paths = spec.get("paths", [])
    globs = spec.get("glob", [])
    globs = [globs] if isinstance(globs, str) else globs
    if not isinstance(paths, list) or not all(isinstance(p, str) for p in paths):
        problems.append(f"{where} paths = {paths!r}: expected a list of folder names")
        paths = []
    if not isinstance(globs, list) or not all(isinstance(g, str) for g in globs):
        problems.append(f"{where} glob = {globs!r}: expected a pattern or a list of patterns")
        globs = []
    found: list[Path] = []
    for p in paths:
        d = Path(os.path.normpath(root / p))
        if not (d / "case.toml").is_file():
            problems.append(f"{where} paths: '{p}' is not a case folder ({d / 'case.toml'} not "
                            "found); fix the path (relative to the study file)")
        else:
            found.append(d)
    for g in globs:
        hits = sorted(Path(h) for h in globmod.glob(str(root / g)) if (Path(h) / "case.toml").is_file())
        if not hits:
            problems.append(f"{where} glob = {g!r}: matches no case folder (a folder holding "
                            f"case.toml) under {root}")
        found += [Path(os.path.normpath(h)) for h in hits]
    cases: list[CaseRef] = []
    seen: dict[str, Path] = {}
    for d in dict.fromkeys(found):  # de-duplicated, order kept
        cid = case_id_of(d)
        if cid in seen:
            problems.append(f"{where}: case id '{cid}' used by both {seen[cid]} and {d}; give each "
                            "case a distinct [case] id")
        seen[cid] = d
        cases.append(CaseRef(d, cid))
    if not cases and not problems:
        problems.append(f"{where}: no cases; list at least one case folder")
    return cases, problems


def load_study(path: str | os.PathLike, *, out: str | os.PathLike | None = None,
               cache: str | os.PathLike | None = None, workers: int | None = None,
               runner: str | None = None) -> Study:
    """Read and validate a study TOML; keyword options override ``[study]`` values.

    Raises
    ------
    ConfigError
        Every problem found, each naming the file and key.  Nothing is written.
    """
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise ConfigError(f"{where}: study file not found; give the path of a study TOML "
                          "(see pipelines/example_study.toml)")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{where}: invalid TOML: {exc}; fix the syntax") from None
    root = path.resolve().parent
    problems: list[str] = []
    warnings: list[str] = []
    for k in doc:
        if k not in TOP_LEVEL:
            near = closest_key(k, TOP_LEVEL)
            problems.append(f"{where}: unknown section [{k}]" + (f" (did you mean [{near}]?)" if near else ""))
    st, p, w = parse_section(StudyTable, doc.get("study"), where=f"{where} [study]")
    problems += p + [f"{where} [study] {q}" for q in st.check()]
    warnings += w
    cases, p = _parse_cases(doc.get("cases"), root=root, where=f"{where} [cases]")
    problems += p
    parameters, p, w = _parse_parameters(doc.get("parameters"), where=f"{where} [parameters]")
    problems += p
    warnings += w
    overrides, p, w = P.check_overrides(doc.get("overrides"), where=f"{where} [overrides]")
    problems += p
    warnings += w
    if st.combine == "zip" and len({len(v) for v in parameters.values()}) > 1:
        problems.append(f"{where} [study] combine = 'zip': every parameter needs the same number "
                        f"of values (got {({k: len(v) for k, v in parameters.items()})})")
    if "tumour_ratio" in parameters and not P.has_c1(overrides, list(parameters)):
        problems.append(f"{where} [parameters] tumour_ratio: needs the tissue c1; vary c1 too or "
                        "set [overrides.mechanics] tissue_c1_kpa")
    if runner is not None:
        from regtrack.study.runner import known_runners, unknown_runner_message

        if runner not in known_runners():
            problems.append(unknown_runner_message(runner).replace("runner = ", "--runner ", 1))
    if workers is not None and workers < 0:
        problems.append(f"workers = {workers}: must be >= 0 (0 = sized to the machine)")
    if problems:
        raise _fail(problems)
    out_dir = Path(out) if out is not None else (root / st.out if st.out else root / f"{path.stem}_results")
    cache_dir = Path(cache) if cache is not None else (root / st.cache if st.cache else out_dir / "cache")
    return Study(path=path.resolve(), name=st.name, cases=tuple(cases), parameters=parameters,
                 combine=st.combine, views=tuple(st.views), outputs=tuple(st.outputs),
                 overrides=overrides, out_dir=out_dir.resolve(), cache_dir=cache_dir.resolve(),
                 runner=runner or st.runner, workers=st.workers if workers is None else workers,
                 retries=st.retries, memory_per_run_gb=st.memory_per_run_gb,
                 warnings=tuple(warnings))
