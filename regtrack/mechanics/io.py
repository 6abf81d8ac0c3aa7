"""Result files of ``regtrack simulate`` (docs/design.md, "File contracts between stages").

* ``R.vtu``: the model mesh with point data ``displacement`` (final, mm),
  ``displacement_<k>_<name>`` after every step (mm) and ``reaction`` (final, N: force of
  the supports on the body at constrained nodes, zero elsewhere);
* ``R.json``: per-step solver statistics and chest-wall reaction (N), totals, and the
  configuration used (for reproducibility).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.mechanics.types import Deformation
from regtrack.model.types import SKIN, BreastModel


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_") or "step"


def save_result(path: str | Path, model: BreastModel, deformation: Deformation, *, config: dict,
                extra: dict | None = None) -> tuple[Path, Path]:
    """Write ``path`` (.vtu) and its ``.json`` sidecar atomically; return both paths."""
    import meshio

    path = Path(path)
    pdata = {"fixed": model.fixed.astype(np.int8)}
    for k, st in enumerate(deformation.steps, start=1):
        pdata[f"displacement_{k}_{_safe(st.name)}"] = st.u
    pdata["displacement"] = deformation.u
    pdata["reaction"] = deformation.steps[-1].reaction
    ntri = len(model.skin)
    mesh = meshio.Mesh(model.points, [("tetra", model.tets), ("triangle", model.skin)], point_data=pdata,
                       cell_data={"region": [model.region.astype(np.int32), np.full(ntri, SKIN, np.int32)]})
    with _io.atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")
    summary = {
        "result": path.name,
        "units": {"displacement": "mm", "force": "N", "time": "s"},
        "steps": [{"index": k, "name": st.name, "chest_wall_reaction_n": st.chest_wall_reaction_n,
                   "max_displacement_mm": float(np.linalg.norm(st.u, axis=1).max()),
                   "nipple_displacement_mm": st.u[model.nipple], **st.stats.to_dict()}
                  for k, st in enumerate(deformation.steps, start=1)],
        "solver": deformation.stats.to_dict(),
        "config": config,
        **(extra or {}),
    }
    side = path.with_suffix(".json")
    _io.write_json(side, summary)
    return path, side
