"""Resolving ``case.toml`` paths safely inside the case folder.

Every input path of a case is relative to the case folder and must stay inside it: an
absolute path, a ``..`` that climbs out, or a symbolic link pointing outside are errors.
This keeps a case folder self-contained (it can be copied, archived or sent to a cluster
worker as one unit) and stops a shared ``case.toml`` from reading arbitrary files.
"""

from __future__ import annotations

import os
from pathlib import Path, PureWindowsPath
from typing import Literal


def _suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def resolve_inside(root: Path, value: str, *, at: str, kind: Literal["file", "dir"] = "file",
                   suffixes: tuple[str, ...] | None = None) -> tuple[Path | None, str | None]:
    """Resolve ``value`` (from ``case.toml``) against the case folder ``root``.

    Parameters
    ----------
    root : Path
        Absolute case folder.
    value : str
        The path as written in ``case.toml``.
    at : str
        Location for messages, e.g. ``"case.toml [views.CC] mammogram"``.
    kind : {"file", "dir"}
        What the path must be.
    suffixes : tuple of str, optional
        Accepted (lower-case) suffixes, e.g. ``(".nii", ".nii.gz")``.

    Returns
    -------
    (path, problem)
        The absolute path (symlinks kept as written) and None, or None and a one-line
        problem naming ``at``, the value and the fix.
    """
    shown = f"{at} = {value!r}"
    if not value.strip():
        return None, f"{shown}: empty path; give a path relative to the case folder"
    if os.path.isabs(value) or PureWindowsPath(value).is_absolute() or value.startswith("~"):
        return None, (f"{shown}: absolute paths are not allowed; copy the file into the case "
                      "folder and give a path relative to it")
    root = Path(os.path.abspath(root))
    candidate = Path(os.path.normpath(root / value))
    if not candidate.is_relative_to(root):
        return None, (f"{shown}: the path leaves the case folder; copy the file into the case "
                      "folder and give a path relative to it")
    if not candidate.exists() and not candidate.is_symlink():
        what = "folder" if kind == "dir" else "file"
        return None, (f"{shown}: {what} not found in {root}; fix the path (relative to the "
                      "case folder)")
    real = candidate.resolve()
    if not real.is_relative_to(root.resolve()):
        return None, (f"{shown}: resolves to {real}, outside the case folder (symbolic link); "
                      "copy the target into the case folder instead of linking to it")
    if not candidate.exists():
        return None, f"{shown}: broken symbolic link; fix or replace it"
    if kind == "file" and not candidate.is_file():
        return None, f"{shown}: is a folder, expected a file; name the file itself"
    if kind == "dir" and not candidate.is_dir():
        return None, f"{shown}: is a file, expected a folder (a DICOM series folder)"
    if suffixes is not None and _suffix(candidate) not in suffixes:
        return None, (f"{shown}: unsupported file type '{_suffix(candidate) or '(none)'}'; "
                      "use one of " + ", ".join(suffixes))
    return candidate, None


def strip_path(message: str, path: Path) -> str:
    """Drop a leading ``"<path>: "`` from a reader's message (the caller names the file)."""
    for prefix in (f"{path}: ", f"{path.name}: "):
        if message.startswith(prefix):
            return message[len(prefix):]
    return message
