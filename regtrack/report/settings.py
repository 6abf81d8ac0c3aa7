"""The report's appendix: the settings that differ from the defaults, and provenance.

The full configuration is in ``provenance.json`` beside the report; the PDF lists only
what a reader needs to reproduce the run: what was changed, with which code, from which
inputs (by SHA-256, never by a path that may name the patient).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from regtrack.config import to_table
from regtrack.report.fmt import value_text


def _flat(table: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in table.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return abs(a - b) <= 1e-12 * max(1.0, abs(a), abs(b))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def changed_settings(configs: dict[str, Any], protocol_overrides: dict | None = None
                     ) -> list[tuple[str, str, str]]:
    """``(setting, value, default)`` of every setting that differs from its default.

    ``configs``: the effective config dataclass of each section (``RunContext.configs``);
    the defaults are those of a freshly constructed one.  ``protocol_overrides``: the
    ``[protocol.<VIEW>]`` tables of the case and the command line (every entry differs
    from the shipped protocol, by construction).
    """
    rows: list[tuple[str, str, str]] = []
    for section, obj in configs.items():
        if not dataclasses.is_dataclass(obj):
            continue
        now, default = _flat(to_table(obj)), _flat(to_table(type(obj)()))
        for key, value in now.items():
            if key not in default or not _same(value, default[key]):
                rows.append((f"{section}.{key}", value_text(value),
                             value_text(default.get(key)) if key in default else "–"))
    for view, table in (protocol_overrides or {}).items():
        for key, value in _flat(dict(table or {})).items():
            rows.append((f"protocol.{view}.{key}", value_text(value), "shipped protocol"))
    return rows


def provenance_rows(prov: dict) -> list[tuple[str, str]]:
    """``(item, value)`` lines of the provenance: versions, platform, inputs by hash,
    cache keys and timings."""
    rows: list[tuple[str, str]] = []
    versions = prov.get("versions") or {}
    if versions:
        rows.append(("Versions", ", ".join(f"{k} {v}" for k, v in versions.items())))
    if prov.get("platform"):
        rows.append(("Platform", str(prov["platform"])))
    for name, digest in (prov.get("inputs") or {}).items():
        rows.append((f"Input {name}", f"SHA-256 {str(digest)[:16]}…"))
    keys = prov.get("stage_keys") or {}
    if keys:
        rows.append(("Cache keys", ", ".join(f"{k} {v}" for k, v in keys.items())))
    timings = prov.get("timings_s") or {}
    if timings:
        main = {k: v for k, v in timings.items() if not k.startswith(("virtual_", "real_"))}
        rows.append(("Run time (s)", ", ".join(f"{k.replace('_', ' ')} {v:.1f}"
                                                for k, v in main.items())))
    return rows
