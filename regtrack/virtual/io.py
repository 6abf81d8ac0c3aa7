"""Reading simulation results for projection (result file contract of docs/design.md).

A result is a ``.vtu`` on the model's nodes with point data ``displacement`` (mm, the
final state) and, per protocol step, ``displacement_<step>``; a JSON sidecar (same stem)
may hold ``plate_frame`` (:meth:`regtrack.virtual.frames.PlateFrame.to_dict`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.errors import InputFileError
from regtrack.model.types import BreastModel

log = logging.getLogger(__name__)


def step_array_names(step: str) -> list[str]:
    """Point-data names accepted for the displacement of ``step``."""
    return [f"displacement_{step}", f"displacement/{step}", f"displacement:{step}", step]


def read_result_positions(path: str | Path, model: BreastModel, *, step: str | None = None) -> np.ndarray:
    """Deformed positions ``points + displacement`` (N, 3) mm of a result ``.vtu``.

    Raises
    ------
    InputFileError
        Missing file, missing/ill-shaped displacement array (the message lists the point
        data present), or a node count different from the model's.
    """
    path = Path(path)
    mesh = _io.read_mesh(path, what="result", made_by="regtrack simulate")
    names = ["displacement"] if step is None else step_array_names(step)
    key = next((n for n in names if n in mesh.point_data), None)
    if key is None:
        have = ", ".join(sorted(mesh.point_data)) or "none"
        what = "'displacement'" if step is None else f"'displacement_{step}'"
        raise InputFileError(f"{path}: point data {what} missing (present: {have}); "
                             "pick one with --step")
    u = np.asarray(mesh.point_data[key], float)
    if u.shape != model.points.shape:
        raise InputFileError(f"{path}: point data '{key}' has shape {u.shape}, the model has "
                             f"{model.points.shape}; the result belongs to another model")
    if not np.isfinite(u).all():
        raise InputFileError(f"{path}: point data '{key}' has non-finite values; the "
                             "simulation did not converge (see its JSON)")
    return model.points + u


def result_plate_angle(path: str | Path, view: str) -> float | None:
    """Plate angle (deg) recorded in the result's JSON sidecar for ``view``, if any."""
    sc = Path(path).with_suffix(".json")
    if not sc.is_file():
        return None
    try:
        doc = json.loads(sc.read_text())
    except ValueError as exc:
        raise InputFileError(f"{sc}: invalid JSON ({exc})") from exc
    pf = doc.get("plate_frame") or doc.get("protocol", {}).get("plate_frame") or {}
    if pf.get("view", "").upper() == view.upper() and pf.get("angle_deg") is not None:
        log.info("plate angle %.1f deg from %s", pf["angle_deg"], sc.name)
        return float(pf["angle_deg"])
    return None
