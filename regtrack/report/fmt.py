"""Numbers and tables as a reader sees them: rounded, signed only when non-zero, no empty
columns.

Every figure printed in the report goes through :func:`num`, so no cell shows 17 digits
or a "-0"; every table goes through :func:`drop_empty_columns`.
"""

from __future__ import annotations

import math
from typing import Any

#: what a missing value looks like
MISSING = "–"


def num(value: Any, decimals: int = 2, *, unit: str = "", signed: bool = False) -> str:
    """``value`` rounded to ``decimals``; "-0.00" becomes "0.00"; None/NaN give "–".

    ``signed``: a leading "+" on positive values (rotations); ``unit`` is appended after a
    space (degrees without one).  Non-numbers are returned as ``str(value)``.
    """
    if value is None or isinstance(value, bool):
        return MISSING if value is None else ("yes" if value else "no")
    try:
        x = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(x):
        return MISSING
    text = f"{x:.{decimals}f}"
    if float(text) == 0.0:
        text = text.lstrip("-")
    elif signed and x > 0:
        text = "+" + text
    if not unit:
        return text
    return text + unit if unit == "°" else f"{text} {unit}"


def sci(value: Any, digits: int = 1) -> str:
    """A small positive quantity in scientific notation (``7.2e-08``); None gives "–"."""
    if value is None:
        return MISSING
    x = float(value)
    if not math.isfinite(x):
        return MISSING
    return "0" if x == 0 else f"{x:.{digits}e}"


def value_text(value: Any) -> str:
    """A configuration value for humans: floats with up to 6 significant digits, lists
    comma-separated, booleans yes/no, None "none"."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        text = f"{value:.6g}"
        return "0" if text == "-0" else text
    if isinstance(value, (list, tuple)):
        return ", ".join(value_text(v) for v in value) if value else "none"
    if isinstance(value, dict):
        return "; ".join(f"{k} {value_text(v)}" for k, v in value.items())
    return str(value)


def drop_empty_columns(head: list[str], rows: list[list[str]]) -> tuple[list[str], list[list[str]]]:
    """Remove the columns whose every cell is empty or "–"."""
    keep = [j for j in range(len(head)) if any(r[j] not in ("", MISSING) for r in rows)]
    return [head[j] for j in keep], [[r[j] for j in keep] for r in rows]
