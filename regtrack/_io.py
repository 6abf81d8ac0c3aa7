"""Atomic file output, and the reading of the mesh files regtrack writes.

Every file regtrack writes goes through these helpers: the data are written to a
temporary file in the destination folder and then renamed over the target with
:func:`os.replace`, which is atomic on POSIX.  A run killed halfway therefore never
leaves a half-written file that a later run would trust.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temporary name keeps the same suffix (so libraries that choose the format by
    extension, e.g. meshio or matplotlib, still work).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sfx = suffix if suffix is not None else "".join(path.suffixes[-1:])
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{sfx}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_figure(fig: Any, path: str | os.PathLike, *, dpi: int = 130) -> Path:
    """Atomically save the matplotlib figure ``fig`` (format from the suffix), then close
    it in pyplot, which otherwise keeps every figure it made alive.

    A figure made without pyplot (``matplotlib.figure.Figure()``) is not known to it; pyplot
    is not imported for it.
    """
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or None)
    finally:
        plt = sys.modules.get("matplotlib.pyplot")
        if plt is not None:
            plt.close(fig)
    return path


def read_mesh(path: str | os.PathLike, *, what: str, made_by: str) -> Any:
    """The :mod:`meshio` mesh in ``path``, a ``.vtu`` that ``made_by`` (a command) writes.

    Raises :class:`~regtrack.errors.InputFileError` naming ``what`` the file is when it is
    missing or unreadable (meshio raises many exception types).
    """
    import meshio

    from regtrack.errors import InputFileError

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: {what} file not found (run `{made_by}` first)")
    try:
        return meshio.read(path)
    except Exception as exc:  # meshio raises many types
        raise InputFileError(f"{path}: cannot read the {what} ({exc}); expected a .vtu from "
                             f"`{made_by}`") from exc


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "__dataclass_fields__"):
        import dataclasses

        return dataclasses.asdict(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def to_json(obj: Any, *, indent: int | None = 2) -> str:
    """JSON text of ``obj``; numpy arrays/scalars, paths and dataclasses are converted."""
    return json.dumps(obj, indent=indent, default=_json_default, allow_nan=False)


def write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 2) -> Path:
    """Atomically write ``obj`` as JSON (NaN/inf are refused: they would be invalid JSON)."""
    return write_text(path, to_json(obj, indent=indent) + "\n")
