"""Override sections of ``case.toml`` and the stage config class each one feeds.

Each pipeline stage owns its configuration dataclass (fields made with
:func:`regtrack.config.param`).  A case may override any of their fields in the matching
section; the table :data:`SECTIONS` maps the section to ``"module:Class"``.  Classes are
imported lazily, so ``regtrack validate`` only imports what it needs.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from regtrack.case._paths import resolve_inside, strip_path
from regtrack.config import closest_key, parse_section
from regtrack.views import SIMULATED_VIEWS


#: Section of ``case.toml`` -> "module:Class" of the stage config it overrides.
SECTIONS: dict[str, str] = {
    "model": "regtrack.model.config:MeshConfig",
    "mechanics": "regtrack.mechanics.config:MechanicsConfig",
    "contact": "regtrack.mechanics.contact:ContactConfig",
    "protocol.CC": "regtrack.mechanics.protocol:ProtocolOverrides",
    "protocol.MLO": "regtrack.mechanics.protocol:ProtocolOverrides",
    "protocol.BIOPSY": "regtrack.mechanics.protocol:ProtocolOverrides",
    "registration": "regtrack.registration.config:RegistrationConfig",
    "virtual": "regtrack.virtual.config:VirtualConfig",
    "tracking": "regtrack.tracking.config:TrackingConfig",
}


def config_class(section: str) -> type:
    """The config dataclass of ``section``; :class:`KeyError` for a section not in
    :data:`SECTIONS`."""
    modname, clsname = SECTIONS[section].split(":")
    return getattr(importlib.import_module(modname), clsname)


def parse_overrides(doc: dict, *, where: str) -> tuple[dict[str, tuple[dict, Any]], list[str],
                                                       list[str]]:
    """Parse every override section present in the TOML document ``doc``.

    Returns ``({section: (table, config_or_None)}, problems, warnings)``.  ``[protocol]``
    must hold only the view tables ``[protocol.CC]`` / ``[protocol.MLO]`` /
    ``[protocol.BIOPSY]``.
    """
    problems: list[str] = []
    warnings: list[str] = []
    tables: dict[str, dict] = {}
    for top in ("model", "mechanics", "contact", "registration", "virtual", "tracking"):
        if top in doc:
            tables[top] = doc[top]
    if "protocol" in doc:
        proto = doc["protocol"]
        if not isinstance(proto, dict):
            problems.append(f"{where} protocol = {proto!r}: expected a table; write the "
                            "overrides as [protocol.CC] / [protocol.MLO] tables")
        else:
            for name, sub in proto.items():
                if name in SIMULATED_VIEWS:
                    tables[f"protocol.{name}"] = sub
                elif isinstance(sub, dict):
                    near = closest_key(name, SIMULATED_VIEWS)
                    problems.append(
                        f"{where} [protocol.{name}]: unknown view '{name}'; valid views: "
                        + ", ".join(SIMULATED_VIEWS)
                        + (f" (did you mean '{near}'?)" if near else ""))
                else:
                    problems.append(
                        f"{where} [protocol] {name} = {sub!r}: protocol overrides belong in "
                        f"a view table; move it to [protocol.CC] and/or [protocol.MLO]")
    out: dict[str, tuple[dict, Any]] = {}
    for section, table in tables.items():
        at = f"{where} [{section}]"
        if not isinstance(table, dict):
            problems.append(f"{where} {section} = {table!r}: expected a table [{section}]")
            continue
        obj, p, w = parse_section(config_class(section), table, where=at)
        problems += p
        warnings += w
        out[section] = (table, obj)
    return out, problems, warnings


def check_protocol_files(parsed: dict[str, tuple[dict, Any]], root: Path, *, where: str,
                         deep: bool) -> list[str]:
    """``[protocol.<V>] protocol = FILE`` must be a ``.toml`` inside the case folder; with
    ``deep`` the file is also parsed and must be a protocol of view ``<V>``."""
    problems: list[str] = []
    for section, (table, cfg) in parsed.items():
        value = getattr(cfg, "protocol", None) if section.startswith("protocol.") else None
        if not isinstance(value, str):
            continue
        at = f"{where} [{section}] protocol"
        path, prob = resolve_inside(root, value, at=at, suffixes=(".toml",))
        if prob:
            problems.append(prob)
            continue
        if deep:
            from regtrack.errors import RegtrackError
            from regtrack.mechanics.protocol import protocol_for_view

            try:
                protocol_for_view(section.split(".")[1], table, where=where, base_dir=root)
            except RegtrackError as exc:
                problems.append(f"{at} = {value!r}: {strip_path(str(exc), path)}")  # type: ignore[arg-type]
    return problems
