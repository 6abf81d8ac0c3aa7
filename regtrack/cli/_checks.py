"""Checks of command-line arguments made before any work starts.

A bad output folder or an out-of-range number used to surface after minutes of meshing
and simulation (or as 8 minutes of mesher retries); each check here raises a
:class:`~regtrack.errors.ConfigError` (or :class:`~regtrack.errors.InputFileError`) whose
one-line message names the option, the value and the fix.  Nothing is created: a folder
that does not exist yet is checked through its nearest existing parent.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from regtrack.errors import ConfigError, InputFileError


def writable_folder(value: str | os.PathLike | None, option: str) -> Path | None:
    """``value`` as a folder regtrack may create or write into, or None when not given.

    Refuses a path naming an existing file, a folder without write permission (for this
    user: ``os.access``, which also reports a read-only file system), and a folder whose
    nearest existing parent is a file or cannot be written.
    """
    if value is None:
        return None
    path = Path(value).expanduser()
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {value}: is a file, not a folder; give a folder path "
                          "(it is created when missing)")
    probe = path
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise ConfigError(f"{option} {value}: {probe} is a file, so the folder cannot be "
                          "created; give another path")
    if not os.access(probe, os.W_OK | os.X_OK):
        what = "folder is" if probe == path else f"parent folder {probe} is"
        raise ConfigError(f"{option} {value}: the {what} not writable (read-only); give a "
                          f"writable {option} folder")
    return path


def number_in_range(value: float | int | None, option: str, *, unit: str = "",
                    gt: float | None = None, ge: float | None = None,
                    le: float | None = None, why: str = "") -> None:
    """Refuse a non-finite number or one outside the stated bounds (None passes)."""
    if value is None:
        return
    u = f" {unit}" if unit else ""
    bounds = []
    if gt is not None:
        bounds.append(f"> {gt:g}{u}")
    if ge is not None:
        bounds.append(f">= {ge:g}{u}")
    if le is not None:
        bounds.append(f"<= {le:g}{u}")
    bad = (not math.isfinite(value) or (gt is not None and not value > gt)
           or (ge is not None and not value >= ge) or (le is not None and not value <= le))
    if bad:
        reason = f" ({why})" if why else ""
        raise ConfigError(f"{option} {value:g}: must be {' and '.join(bounds)}{reason}")


def existing_file(value: str | os.PathLike | None, option: str, what: str) -> Path | None:
    """``value`` as an existing regular file, or None when not given."""
    if value is None:
        return None
    path = Path(value).expanduser()
    if not path.exists():
        raise InputFileError(f"{option} {value}: {what} not found; check the path")
    if not path.is_file():
        raise InputFileError(f"{option} {value}: is a folder; give the {what} file")
    return path
