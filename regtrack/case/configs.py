"""A case plus one command's overrides -> :class:`Configs`, every stage's typed settings.

Layers, the later wins: each config class's defaults < the case's ``case.toml`` section
(parsed once, by :func:`regtrack.case.load_case`; :meth:`Case.config`) < the command's
overrides (``regtrack run --set``, a study's parameter point or fixed ``[overrides]``,
:func:`regtrack.study.params.apply_point`), parsed here on top of the case's values
(:func:`regtrack.config.parse_section` with ``base``), so each value is parsed once.
Every command and every cache key take their settings from the :class:`Configs` this
module returns.

Values keep the units written in case.toml (kPa for the stiffnesses of ``[mechanics]``);
the mechanics package converts them to its own units (MPa) where it builds the element
materials (:func:`regtrack.mechanics.materials.element_materials`).
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Any

from regtrack.case.overrides import SECTIONS
from regtrack.config import parse_section, to_table, unknown_name
from regtrack.errors import CaseError
from regtrack.views import SIMULATED_VIEWS

#: Sections only a command sets (case.toml has no such section) -> "module:Class".
COMMAND_SECTIONS: dict[str, str] = {
    "virtual": "regtrack.virtual.config:VirtualConfig",
    "tracking": "regtrack.tracking.config:TrackingConfig",
}
#: The config sections of :class:`Configs` besides the protocols.
CONFIG_FIELDS = ("model", "mechanics", "contact", "registration", "virtual", "tracking")


@dataclass(frozen=True)
class Configs:
    """The settings of one run of a case.

    Attributes
    ----------
    model, mechanics, contact, registration, virtual, tracking
        The config dataclass of each stage (:data:`SECTIONS`, :data:`COMMAND_SECTIONS`).
    protocols : dict of str to Protocol
        The compression protocol of each view (:func:`regtrack.mechanics.protocol.protocol_for_view`).
    protocol_tables : dict of str to dict
        Each view's ``[protocol.<VIEW>]`` table as written (case.toml < overrides).
    overrides : dict
        The command's overrides as given (case.toml layout), for provenance.
    """

    model: Any
    mechanics: Any
    contact: Any
    registration: Any
    virtual: Any
    tracking: Any
    protocols: dict[str, Any] = field(default_factory=dict)
    protocol_tables: dict[str, dict] = field(default_factory=dict)
    overrides: dict = field(default_factory=dict)

    def with_protocol_tables(self, case: Any, tables: dict[str, dict]) -> Configs:
        """These configs with the views' ``[protocol.<VIEW>]`` tables replaced (e.g. by the
        plate gap and angle read from the DICOM, :mod:`regtrack.pipeline.geometry`) and
        their protocols parsed again."""
        from regtrack.mechanics.protocol import protocol_for_view

        merged = {**self.protocol_tables, **{v: dict(t) for v, t in tables.items()}}
        protocols = {**self.protocols,
                     **{v: protocol_for_view(v, merged[v] or None, where=str(case.toml_path),
                                             base_dir=case.root) for v in tables}}
        return dataclasses.replace(self, protocols=protocols, protocol_tables=merged)

    def to_tables(self) -> dict[str, dict]:
        """Plain tables of every config section (written into provenance and reports)."""
        return {name: to_table(getattr(self, name)) for name in CONFIG_FIELDS}


def _command_class(section: str) -> type:
    modname, clsname = COMMAND_SECTIONS[section].split(":")
    return getattr(importlib.import_module(modname), clsname)


def resolve_configs(case: Any, overrides: dict | None = None) -> Configs:
    """The :class:`Configs` of ``case`` with the command's ``overrides`` applied.

    ``overrides`` uses the case.toml layout: ``{"mechanics": {"tissue_c1_kpa": 1.0},
    "protocol": {"CC": {"target_D": 0.38}}}``.  A bad value, an unknown key or an unknown
    section in ``overrides`` raises :class:`CaseError` naming it (a run must not silently
    ignore a setting it was given).
    """
    overrides = dict(overrides or {})
    where = str(case.toml_path)
    problems: list[str] = []
    known = (*CONFIG_FIELDS, "protocol")
    problems += [unknown_name("overrides", "section", name, known)
                 for name in overrides if name not in known]
    values: dict[str, Any] = {}
    for name in CONFIG_FIELDS:
        base = case.config(name) if name in SECTIONS else _command_class(name)()
        table = overrides.get(name)
        if table:
            base, p, w = parse_section(type(base), table, where=f"overrides [{name}]", base=base)
            problems += p + [x.replace("' ignored", "'") for x in w]
        values[name] = base
    proto_over = overrides.get("protocol") or {}
    for view in proto_over:
        if view not in SIMULATED_VIEWS:
            problems.append(f"overrides [protocol.{view}]: unknown view '{view}'; use "
                            + ", ".join(SIMULATED_VIEWS))
    if problems:
        raise CaseError(problems)
    from regtrack.mechanics.protocol import protocol_for_view

    tables = {v: {**case.override_table(f"protocol.{v}"), **dict(proto_over.get(v) or {})}
              for v in SIMULATED_VIEWS}
    protocols = {v: protocol_for_view(v, tables[v] or None, where=where, base_dir=case.root)
                 for v in SIMULATED_VIEWS}
    from regtrack.mechanics.placement import edge_wedge_problem

    wedge = [f"{where} [protocol.{v}]: {msg}" for v, pr in protocols.items()
             if (msg := edge_wedge_problem(pr.plates.posterior_edge_mm, pr.plates.edge_radius_mm,
                                           values["contact"]))]
    if wedge:
        raise CaseError(wedge)
    return Configs(**values, protocols=protocols, protocol_tables=tables, overrides=overrides)
