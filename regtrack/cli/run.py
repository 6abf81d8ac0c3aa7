"""regtrack run CASE: mesh -> simulate each view -> virtual mammogram -> real mammogram
-> align -> metrics -> report."""

from __future__ import annotations

import argparse

HELP = "run the whole pipeline on a case and write the report (metrics, figures, PDF)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("case", help="case folder (holding case.toml) or the case.toml itself")
    p.add_argument("--views", default=None, help="comma-separated views, e.g. cc,mlo (default: all in the case)")
    p.add_argument("--out", default=None, help="output folder (default: reports/<case id>)")
    p.add_argument("--cache", default=None,
                   help="stage cache folder; finished stages are re-used (default: .regtrack-cache)")
    p.add_argument("--no-report", action="store_true", help="metrics only, no figures or PDF")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a case.toml setting for this run, e.g. --set model.target_nodes=3000 "
                        "or --set protocol.CC.target_D=0.3 (VALUE is a TOML literal; repeatable)")
    p.add_argument("--keep-identifiers", action="store_true",
                   help="copy the DICOM patient identifiers into provenance.json (default: none "
                        "reaches any output, log or figure; the case id is checked too)")
    p.add_argument("--serial-views", action="store_true",
                   help="simulate the views one after the other (default: at the same time, one "
                        "process each, when two or more cores are free)")


def run(args: argparse.Namespace) -> int:
    import logging
    import time
    from pathlib import Path

    from rich.console import Console

    from regtrack.case import load_case
    from regtrack.cli._console import SimulationProgress
    from regtrack.pipeline.run import run_case
    from regtrack.cli._checks import writable_folder
    from regtrack.privacy import Identifiers, identifiers_of_case_folder, pseudonymous_id, scrub_logs

    console = Console(stderr=True)
    quiet = bool(getattr(args, "quiet", False))
    # everything the command line decides is checked before the case is read or any
    # stage runs: the override keys and the folders written at the end
    overrides = parse_sets(args.set)
    writable_folder(args.out, "--out")
    writable_folder(args.cache, "--cache")
    t0 = time.perf_counter()
    # stage messages go to the console; keep library INFO logs for --debug
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        logging.getLogger("regtrack").setLevel(logging.WARNING)
        logging.getLogger("highdicom").setLevel(logging.WARNING)  # its INFO lines per attribute
    with SimulationProgress(console) as shown:  # from here on, each warning once
        found = identifiers_of_case_folder(args.case)
        with scrub_logs(Identifiers() if args.keep_identifiers else found):
            case = load_case(args.case, deep=False)
        case_id = case.id if args.keep_identifiers else pseudonymous_id(case.id, found)
        out = Path(args.out) if args.out else Path("reports") / case_id
        writable_folder(out, "--out")
        views = tuple(v.strip().upper() for v in args.views.split(",")) if args.views else None
        rows = run_case(args.case, overrides=overrides, views=views, cache_dir=args.cache,
                        out_dir=out, progress=None if quiet else shown.say,
                        sim_progress=None if quiet else shown.increment,
                        report=not args.no_report, keep_identifiers=args.keep_identifiers,
                        concurrent=False if args.serial_views else None)
    if quiet:
        return 0
    for r in rows:
        def f(k, fmt):
            v = r.get(k)
            return "–" if v is None else format(v, fmt)
        console.print(f"[bold]{r['view']}[/bold]: BS_Av {f('BS_Av', '.1f')} %  TS_Av {f('TS_Av', '.1f')} %  "
                      f"θp {f('theta_p', '.2f')}°  D {f('D', '.3f')}  d_T {f('d_T', '.2f')} mm  "
                      f"d_B {f('d_B', '.2f')} mm")
    console.print(f"report written to {out} ({time.perf_counter() - t0:.1f} s)")
    return 0


def parse_sets(items: list[str]) -> dict:
    """``["model.target_nodes=3000", "protocol.CC.target_D=0.3"]`` -> nested overrides.

    Each item is checked against the configuration schema (the stage config dataclasses of
    :data:`regtrack.case.overrides.SECTIONS` and ``[virtual]``) before anything runs: an
    unknown section or key is an error naming the closest valid one, a bad value an error
    naming the allowed range.
    """
    import tomllib

    from regtrack.errors import ConfigError

    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        parts = [k.strip() for k in key.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise ConfigError(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. "
                              "--set model.target_nodes=3000")
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            parsed = value.strip()  # a bare word is a string
        _check_set(item, parts, parsed)
        node = out
        for k in parts[:-1]:
            node = node.setdefault(k, {})
        node[parts[-1]] = parsed
    return out


def _set_sections() -> dict[str, type]:
    """Section name (``model``, ``protocol.CC``, ...) -> its config dataclass."""
    from regtrack.case.overrides import SECTIONS, config_class
    from regtrack.virtual.config import VirtualConfig

    out: dict[str, type] = {}
    for section in SECTIONS:
        cls = config_class(section)
        if cls is not None:
            out[section] = cls
    out["virtual"] = VirtualConfig
    return out


def _check_set(item: str, parts: list[str], value) -> None:
    """One ``--set`` item against the schema; raises :class:`ConfigError` (one line)."""
    from regtrack.config import closest_key, parse_section
    from regtrack.errors import ConfigError

    sections = _set_sections()
    n = 2 if parts[0] == "protocol" else 1
    section = ".".join(parts[:n])
    if section not in sections:
        near = closest_key(section, sections)
        hint = f" (did you mean '{near}'?)" if near else ""
        raise ConfigError(f"--set {item}: unknown section '{section}'{hint}; sections: "
                          f"{', '.join(sections)}")
    keys = parts[n:]
    if not keys:
        raise ConfigError(f"--set {item}: give a key of [{section}], e.g. --set {section}."
                          f"{next(iter(_fields(sections[section])))}=VALUE")
    table: dict = {}
    node = table
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    where = f"--set {item} [{section}]"
    # the checks between keys (e.g. formulation 'p2' needs skin_enabled = false) wait for
    # the whole configuration: case.toml and every --set (resolve_configs, before any work)
    _obj, problems, warnings = parse_section(sections[section], table, where=where,
                                             cross_checks=False)
    if warnings:  # an unknown key: an error here, since the value would be ignored
        import re

        m = re.search(r"unknown key '(.+?)' ignored(?: \(did you mean '(.+?)'\?\))?", warnings[0])
        table_name = ".".join([section, *keys[:-1]])
        bad, near = (m.group(1), m.group(2)) if m else (keys[-1], None)
        hint = f" (did you mean '{near}'?)" if near else ""
        raise ConfigError(f"--set {item}: unknown key '{bad}' in [{table_name}]{hint}")
    if problems:
        raise ConfigError(problems[0].replace(f"{where} ", f"--set {item}: [{section}] ", 1))


def _fields(cls: type) -> list[str]:
    import dataclasses

    return [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
