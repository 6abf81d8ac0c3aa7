"""Typed configuration sections parsed from TOML, with validation that names the key.

Every physical parameter lives in a dataclass whose fields carry their unit, range and
documentation in ``metadata``; :func:`parse_section` turns a TOML table into that
dataclass and collects *all* problems (wrong type, out of range, unknown key) instead
of stopping at the first.  Example::

    @dataclass(frozen=True)
    class Materials:
        c1_kpa: float = param(0.54, "kPa", "neo-Hookean c1 of the tissue", gt=0)
        nu: float = param(0.49, "-", "Poisson's ratio", ge=0.0, lt=0.5)

    mats, problems, warnings = parse_section(Materials, {"nu": 0.5}, where="case.toml [mechanics]")
    # problems == ["case.toml [mechanics] nu = 0.5: must be < 0.5 (Poisson's ratio)"]
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from typing import Any, TypeVar

from regtrack.errors import ConfigError

T = TypeVar("T")


def param(default: Any, unit: str = "", doc: str = "", *, gt=None, ge=None, lt=None, le=None,
          choices: tuple | None = None, default_factory=None) -> Any:
    """A dataclass field with unit, documentation and bounds for :func:`parse_section`."""
    md = {"unit": unit, "doc": doc, "gt": gt, "ge": ge, "lt": lt, "le": le, "choices": choices}
    if default_factory is not None:
        return dataclasses.field(default_factory=default_factory, metadata=md)
    return dataclasses.field(default=default, metadata=md)


def closest_key(key: str, valid) -> str | None:
    m = difflib.get_close_matches(key, list(valid), n=1, cutoff=0.5)
    return m[0] if m else None


def unknown_name(where: str, what: str, name: str, valid) -> str:
    """One line for an unknown ``name``: ``"<where>: unknown <what> '<name>' (did you mean
    '<closest>'?); use one of <valid>"``."""
    valid = list(valid)
    near = closest_key(name, valid)
    return (f"{where}: unknown {what} '{name}'" + (f" (did you mean '{near}'?)" if near else "")
            + f"; use one of {', '.join(valid)}")


def _check_type(value: Any, tp: Any) -> tuple[bool, Any]:
    """Return (ok, coerced) for the simple types used in config sections."""
    origin = typing.get_origin(tp)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False, value
        return True, float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return False, value
        return True, value
    if tp is bool:
        return isinstance(value, bool), value
    if tp is str:
        return isinstance(value, str), value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            return False, value
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        out = []
        for v in value:
            ok, cv = _check_type(v, inner) if inner is not Any else (True, v)
            if not ok:
                return False, value
            out.append(cv)
        return True, tuple(out) if origin is tuple else out
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        for a in typing.get_args(tp):
            if a is type(None):
                if value is None:
                    return True, None
                continue
            ok, cv = _check_type(value, a)
            if ok:
                return True, cv
        return False, value
    if tp is Any or tp is dict or origin is dict:
        return True, value
    if dataclasses.is_dataclass(tp):  # a sub-table given as a scalar (fuzzing, issue 53)
        return False, value
    return True, value


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp)).replace("typing.", "")


def parse_assignments(items: list[str], *, where: str = "command line") -> dict[str, Any]:
    """``["key=value", ...]`` (command-line overrides) -> a table for :func:`parse_section`:
    ``true``/``false`` become booleans, then int, then float, else the string is kept."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{where}: '{item}' is not key=value (e.g. friction=0.1)")
        value: Any = {"true": True, "false": False}.get(text.strip().lower(), text.strip())
        if isinstance(value, str):
            for conv in (int, float):
                try:
                    value = conv(value)
                    break
                except ValueError:
                    pass
        out[key.strip()] = value
    return out


def parse_section(cls: type[T], table: dict | None, *, where: str,
                  base: T | None = None, cross_checks: bool = True) -> tuple[T, list[str], list[str]]:
    """Build ``cls`` from a TOML table; return ``(obj, problems, warnings)``.

    Unknown keys are warnings naming the closest valid key.  Wrong types and values out
    of range are problems naming ``where``, the key, the value and the allowed range.
    ``base``: an instance of ``cls`` whose values the table's keys replace (a layer of
    overrides on an already parsed section; nested sections merge the same way); default:
    the class defaults.  When there are problems, ``obj`` holds the base values for the
    offending keys.  ``cross_checks=False`` leaves out the class's ``problems()`` (checks
    between keys), for a table that is one layer of several: its other keys come later.
    """
    table = dict(table or {})
    problems: list[str] = []
    warnings: list[str] = []
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in table.items():
        if key not in fields:
            near = closest_key(key, fields)
            warnings.append(
                f"{where}: unknown key '{key}' ignored" + (f" (did you mean '{near}'?)" if near else "")
            )
            continue
        f = fields[key]
        tp = hints[key]
        md = f.metadata
        doc = f" ({md['doc']})" if md.get("doc") else ""
        if dataclasses.is_dataclass(tp) and isinstance(value, dict):
            sub, p, w = parse_section(tp, value, where=f"{where[:-1]}.{key}]" if where.endswith("]") else f"{where}.{key}",
                                      base=None if base is None else getattr(base, key),
                                      cross_checks=cross_checks)
            problems += p
            warnings += w
            kwargs[key] = sub
            continue
        ok, cv = _check_type(value, tp)
        if not ok:
            problems.append(f"{where} {key} = {value!r}: expected {_type_name(tp)}{doc}")
            continue
        bad = _range_problem(cv, md)
        if bad:
            unit = f" {md['unit']}" if md.get("unit") and md["unit"] != "-" else ""
            problems.append(f"{where} {key} = {value!r}{unit}: {bad}{doc}")
            continue
        kwargs[key] = cv
    obj = cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)  # type: ignore[type-var]
    post = getattr(obj, "problems", None)
    if cross_checks and callable(post) and not problems:
        problems += [f"{where}: {p}" for p in post()]
    return obj, problems, warnings


def _range_problem(v: Any, md: dict) -> str | None:
    if md.get("choices") is not None and v not in md["choices"]:
        return "must be one of " + ", ".join(repr(c) for c in md["choices"])
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return None
    if md.get("gt") is not None and not v > md["gt"]:
        return f"must be > {md['gt']}"
    if md.get("ge") is not None and not v >= md["ge"]:
        return f"must be >= {md['ge']}"
    if md.get("lt") is not None and not v < md["lt"]:
        return f"must be < {md['lt']}"
    if md.get("le") is not None and not v <= md["le"]:
        return f"must be <= {md['le']}"
    return None


def describe(cls: type) -> list[dict]:
    """Rows (key, default, unit, doc, range) documenting a config section."""
    rows = []
    for f in dataclasses.fields(cls):
        md = f.metadata
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)  # type: ignore[misc]
        rng = ", ".join(f"{k} {md[k]}" for k in ("gt", "ge", "lt", "le") if md.get(k) is not None)
        rows.append({"key": f.name, "default": default, "unit": md.get("unit", ""),
                     "doc": md.get("doc", ""), "range": rng, "choices": md.get("choices")})
    return rows


def to_table(obj: Any) -> dict:
    """Plain dict (TOML-ready) of a config dataclass, for writing into outputs."""
    return dataclasses.asdict(obj)


def config_from_assignments(cls: type[T], items: list[str], *, where: str) -> T:
    """``cls`` from command-line ``key=value`` overrides (:func:`parse_assignments`),
    validated like a case.toml section; unknown keys and bad values raise
    :class:`ConfigError` naming ``where``, the key and the allowed values."""
    obj, problems, warnings = parse_section(cls, parse_assignments(items, where=where), where=where)
    if problems or warnings:
        unknown = [w.replace("' ignored", "'") for w in warnings]
        raise ConfigError("; ".join(problems + unknown))
    return obj
