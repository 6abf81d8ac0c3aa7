"""Landmark lists of the MRI: a CSV table or a 3D Slicer markups file, in LPS mm.

Two formats are read:

* **CSV**: one point per row, columns ``x, y, z`` (LPS, mm) and optionally ``name``
  first; a header row naming the columns is optional (``name,x,y,z`` or ``x,y,z``).
* **3D Slicer markups** (``.mrk.json``, the format of Slicer >= 4.11): every control point
  of every markup, named by its ``label``.  Slicer writes ``"coordinateSystem": "LPS"``
  (the default since Slicer 5) or ``"RAS"``; RAS points are converted with
  ``(x, y, z)_LPS = (-x, -y, z)_RAS``.

Every problem is a :class:`~regtrack.errors.TrackingError` naming the file, the row or
point, and the fix.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from regtrack.errors import TrackingError


@dataclass(frozen=True)
class Landmarks:
    """Named points of the MRI.

    Attributes
    ----------
    names : tuple of str
    lps_mm : (M, 3) float
        Positions in the patient frame (DICOM LPS, mm).
    """

    names: tuple[str, ...]
    lps_mm: np.ndarray


def read_landmarks(path: str | Path) -> Landmarks:
    """Read a landmark CSV or a 3D Slicer ``.mrk.json`` file (LPS mm; see the module)."""
    path = Path(path)
    if not path.is_file():
        raise TrackingError(f"--landmarks {path}: file not found; give a CSV (name,x,y,z in "
                            "LPS mm) or a 3D Slicer .mrk.json file")
    if path.name.lower().endswith(".json"):
        names, pts = _read_markups(path)
    else:
        names, pts = _read_csv(path)
    if not pts:
        raise TrackingError(f"{path}: no landmark in the file; give at least one point")
    arr = np.asarray(pts, float)
    return Landmarks(tuple(names), arr)


def _number(text: str, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise TrackingError(f"{where}: {text.strip()!r} is not a number; give x, y, z in "
                            "mm") from None
    if not math.isfinite(v):
        raise TrackingError(f"{where}: {text.strip()!r} must be a finite number of mm")
    return v


def _read_csv(path: Path) -> tuple[list[str], list[list[float]]]:
    names: list[str] = []
    pts: list[list[float]] = []
    with path.open(newline="", encoding="utf-8-sig") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    if rows and rows[0][-1].strip().lower() == "z":  # a header row
        rows = rows[1:]
    for i, row in enumerate(rows, start=1):
        where = f"{path} row {i}"
        cells = [c.strip() for c in row]
        if len(cells) == 3:
            name, xyz = f"P{i}", cells
        elif len(cells) == 4:
            name, xyz = cells[0] or f"P{i}", cells[1:]
        else:
            raise TrackingError(f"{where}: {len(cells)} columns; expected x,y,z or name,x,y,z "
                                "(LPS mm)")
        names.append(name)
        pts.append([_number(c, where) for c in xyz])
    return names, pts


def _read_markups(path: Path) -> tuple[list[str], list[list[float]]]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise TrackingError(f"{path}: not a valid JSON file ({exc}); export the markups from "
                            "3D Slicer as .mrk.json") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list):
        raise TrackingError(f"{path}: no 'markups' list; export the markups from 3D Slicer as "
                            ".mrk.json")
    names: list[str] = []
    pts: list[list[float]] = []
    for m, mk in enumerate(markups):
        system = str(mk.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise TrackingError(f"{path} markup {m + 1}: coordinateSystem {system!r}; expected "
                                "LPS or RAS")
        flip = np.array([-1.0, -1.0, 1.0]) if system == "RAS" else np.ones(3)
        for k, cp in enumerate(mk.get("controlPoints") or []):
            where = f"{path} markup {m + 1} point {k + 1}"
            pos = cp.get("position")
            if not isinstance(pos, list) or len(pos) != 3:
                raise TrackingError(f"{where}: 'position' must be 3 numbers (mm)")
            xyz = np.array([_number(str(v), where) for v in pos]) * flip
            names.append(str(cp.get("label") or f"P{len(names) + 1}"))
            pts.append(xyz.tolist())
    return names, pts
