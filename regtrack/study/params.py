"""Study parameters: names, units, validation and their mapping onto pipeline overrides.

A study varies *parameters*; the pipeline reads *overrides* (TOML-like sections of
``case.toml``).  Each short name maps onto one override key:

============  ========  ==============================================================
name          unit      override
============  ========  ==============================================================
c1            kPa       ``[mechanics] tissue_c1_kpa``
nu            \\-        ``[mechanics] nu``
tumour_ratio  \\-        ``[mechanics] tumour_c1_kpa = tumour_ratio * c1``
friction      \\-        ``[contact] friction``
target_D      \\-        ``[protocol.<VIEW>] target_D`` for every view of the study
mesh_nodes    \\-        ``[model] target_nodes``
============  ========  ==============================================================

Any other override key can be varied by its dotted name, ``"<section>.<key>"``, e.g.
``"registration.bracket_deg"`` or ``"protocol.MLO.target_D"``, where ``<section>`` is one
of :data:`SECTIONS`.  Values are checked against the owning stage's config class
(:mod:`regtrack.case.overrides`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

from regtrack.case.overrides import config_class, parse_overrides
from regtrack.config import closest_key, param, parse_section, unknown_name


#: Override sections a study may set or vary.
SECTIONS = ("model", "mechanics", "contact", "registration", "protocol.CC", "protocol.MLO")

#: Short name -> (section, key); ``<VIEW>`` is replaced by each view of the study.
ALIASES: dict[str, tuple[str, str]] = {
    "c1": ("mechanics", "tissue_c1_kpa"),
    "nu": ("mechanics", "nu"),
    "tumour_ratio": ("mechanics", "tumour_c1_kpa"),
    "friction": ("contact", "friction"),
    "target_D": ("protocol.<VIEW>", "target_D"),
    "mesh_nodes": ("model", "target_nodes"),
}


@dataclass(frozen=True)
class ParameterValues:
    """Range check of one value of each named study parameter."""

    c1: float | None = param(None, "kPa", "tissue neo-Hookean c1 -> [mechanics] tissue_c1_kpa",
                             gt=0, le=1e4)
    nu: float | None = param(None, "-", "tissue Poisson's ratio -> [mechanics] nu", ge=0.0, lt=0.5)
    tumour_ratio: float | None = param(None, "-", "tumour c1 / tissue c1 -> [mechanics] "
                                       "tumour_c1_kpa = tumour_ratio * c1", gt=0, le=1e3)
    friction: float | None = param(None, "-", "skin-plate Coulomb friction -> [contact] friction",
                                   ge=0.0, le=2.0)
    target_D: float | None = param(None, "-", "target compression degree (fraction of breast "
                                   "thickness) -> [protocol.<VIEW>] target_D", gt=0.0, lt=1.0)
    mesh_nodes: int | None = param(None, "-", "target number of mesh nodes -> [model] "
                                   "target_nodes", ge=100, le=5_000_000)


def split_dotted(name: str) -> tuple[str, str] | None:
    """``"protocol.CC.target_D"`` -> ``("protocol.CC", "target_D")``; None if not dotted."""
    if "." not in name:
        return None
    section, key = name.rsplit(".", 1)
    return section, key


def check_value(name: str, value: Any, *, where: str) -> tuple[Any, list[str], list[str]]:
    """Validate one value of parameter ``name``; return ``(coerced, problems, warnings)``."""
    if name in ALIASES:
        obj, problems, warnings = parse_section(ParameterValues, {name: value}, where=where)
        return getattr(obj, name), problems, warnings
    dotted = split_dotted(name)
    if dotted is None or dotted[0] not in SECTIONS:
        near = closest_key(name, list(ALIASES) + [f"{s}." for s in SECTIONS])
        hint = f" (did you mean '{near}'?)" if near else ""
        return value, [f"{where} {name}: unknown parameter{hint}; use one of "
                       f"{', '.join(ALIASES)} or '<section>.<key>' with section in "
                       f"{', '.join(SECTIONS)}"], []
    if isinstance(value, (dict, list)):
        return value, [f"{where} {name} = {value!r}: expected a number, string or boolean"], []
    section, key = dotted
    obj, problems, warnings = parse_section(config_class(section), {key: value}, where=where)
    if warnings:  # an unknown key is an error here: the run would silently ignore it
        return value, warnings, []
    return getattr(obj, key), problems, []


def check_overrides(table: Any, *, where: str) -> tuple[dict, list[str], list[str]]:
    """Validate the study's fixed ``[overrides]`` sections (the case.toml layout, parsed by
    :func:`regtrack.case.overrides.parse_overrides`); return ``(table, problems, warnings)``."""
    if table is None:
        return {}, [], []
    if not isinstance(table, dict):
        return {}, [f"{where}: expected a table of override sections ([overrides.mechanics], ...)"], []
    tops = list(dict.fromkeys(s.split(".")[0] for s in SECTIONS))
    problems = [unknown_name(where, "section", top, tops) for top in table if top not in tops]
    _, p, warnings = parse_overrides(table, where=where)
    return copy.deepcopy(table), problems + p, warnings


def _set(overrides: dict, section: str, key: str, value: Any) -> None:
    node = overrides
    for part in section.split("."):
        node = node.setdefault(part, {})
    node[key] = value


def _get(overrides: dict, section: str, key: str) -> Any:
    node: Any = overrides
    for part in section.split("."):
        node = node.get(part, {}) if isinstance(node, dict) else {}
    return node.get(key) if isinstance(node, dict) else None


def apply_point(base: dict, point: dict[str, Any], *, views: tuple[str, ...]) -> dict:
    """Overrides of one run: ``base`` (the study's fixed overrides) plus a parameter point.

    ``tumour_ratio`` multiplies the run's tissue c1 (from ``c1`` or the fixed overrides).  A
    run that sets the tissue c1 also sets ``tissue_model = "homogeneous"`` unless the study
    names one, so a case with a fat/gland model (case.toml) is varied as the paper's
    homogeneous model rather than silently keeping its own stiffness.

    Raises
    ------
    KeyError
        ``tumour_ratio`` given without any tissue c1 (checked earlier by the study loader).
    """
    out = copy.deepcopy(base)
    for name, value in point.items():
        if name == "tumour_ratio":
            continue
        if name == "target_D":
            for view in views:
                _set(out, f"protocol.{view}", "target_D", value)
        elif name in ALIASES:
            section, key = ALIASES[name]
            _set(out, section, key, value)
        else:
            section, key = split_dotted(name)  # type: ignore[misc]
            _set(out, section, key, value)
    if _get(out, "mechanics", "tissue_c1_kpa") is not None and _get(out, "mechanics", "tissue_model") is None:
        # a study's c1 is the homogeneous tissue's: a case's fat/gland tissue_model would ignore it
        _set(out, "mechanics", "tissue_model", "homogeneous")
    if "tumour_ratio" in point:
        c1 = _get(out, "mechanics", "tissue_c1_kpa")
        if c1 is None:
            raise KeyError("tumour_ratio needs c1")
        _set(out, "mechanics", "tumour_c1_kpa", _round(point["tumour_ratio"] * c1))
    return out


def _round(x: float) -> float:
    """Round to 10 significant digits so equal values give equal cache keys."""
    return float(f"{x:.10g}")


def has_c1(base: dict, names: list[str]) -> bool:
    """Whether a tissue c1 is set (varied or fixed) so ``tumour_ratio`` can be applied."""
    return "c1" in names or "mechanics.tissue_c1_kpa" in names or \
        _get(base, "mechanics", "tissue_c1_kpa") is not None
