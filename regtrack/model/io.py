"""Model file contract (docs/design.md): a meshio-readable ``.vtu`` plus a JSON sidecar.

* tetrahedra carry cell data ``region`` (1 tissue, 2 tumour), ``tumour_id`` and
  ``tissue_label``; triangles carry ``region`` 3 (skin membrane);
* point data ``fixed`` (1 on chest-wall nodes);
* the sidecar ``<name>.json`` holds the nipple node, the anatomical frame, provenance and
  mesh-quality figures.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.errors import InputFileError
from regtrack.model.types import SKIN, AnatomicalFrame, BreastModel


def sidecar_path(path: str | Path) -> Path:
    return Path(path).with_suffix(".json")


def save_model(model: BreastModel, path: str | Path) -> Path:
    """Write ``model`` as ``path`` (.vtu) and its JSON sidecar, atomically."""
    import meshio

    path = Path(path)
    ntet, ntri = len(model.tets), len(model.skin)
    tl = model.tissue_label if model.tissue_label is not None else np.zeros(ntet, int)
    mesh = meshio.Mesh(
        model.points,
        [("tetra", model.tets), ("triangle", model.skin)],
        point_data={"fixed": model.fixed.astype(np.int8)},
        cell_data={
            "region": [model.region.astype(np.int32), np.full(ntri, SKIN, np.int32)],
            "tumour_id": [model.tumour_id.astype(np.int32), np.zeros(ntri, np.int32)],
            "tissue_label": [np.asarray(tl, np.int32), np.zeros(ntri, np.int32)],
        },
    )
    with _io.atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")
    side = {"nipple_node": model.nipple, "frame": model.frame.to_dict(), "meta": model.meta}
    _io.write_json(sidecar_path(path), side)
    return path


def load_model(path: str | Path) -> BreastModel:
    """Read a model written by :func:`save_model` (or by another tool following the contract).

    Without a sidecar, the nipple is taken as the most anterior (+x) node and the frame as
    the identity, with a warning in ``meta``.
    """
    path = Path(path)
    mesh = _io.read_mesh(path, what="model", made_by="regtrack mesh CASE")
    tets = tris = None
    reg_t = tid = tl = None
    for i, block in enumerate(mesh.cells):
        cd = {k: v[i] for k, v in mesh.cell_data.items()}
        if block.type == "tetra":
            tets = block.data
            reg_t = cd.get("region", np.ones(len(tets), int))
            tid = cd.get("tumour_id", (np.asarray(reg_t) == 2).astype(int))
            tl = cd.get("tissue_label")
        elif block.type == "triangle":
            tris = block.data
    if tets is None:
        raise InputFileError(f"{path}: no tetrahedra in the mesh (cell type 'tetra' expected)")
    if "fixed" not in mesh.point_data:
        raise InputFileError(f"{path}: point data 'fixed' missing (1 on chest-wall nodes)")
    fixed = np.asarray(mesh.point_data["fixed"]).astype(bool).reshape(-1)
    meta: dict = {}
    sc = sidecar_path(path)
    if sc.is_file():
        try:
            side = json.loads(sc.read_text())
            nipple = int(side["nipple_node"])
            frame = AnatomicalFrame.from_dict(side["frame"])
            meta = side.get("meta", {})
        except (KeyError, ValueError, TypeError) as exc:
            raise InputFileError(f"{sc}: invalid model sidecar ({exc}); keys 'nipple_node' and 'frame' are required") from exc
    else:
        nipple = int(np.argmax(mesh.points[:, 0]))
        frame = AnatomicalFrame(np.zeros(3), np.eye(3), "R")
        meta = {"warning": f"no sidecar {sc.name}: nipple = most anterior node, identity frame"}
    return BreastModel(
        points=np.asarray(mesh.points, float),
        tets=tets,
        region=np.asarray(reg_t).reshape(-1),
        tumour_id=np.asarray(tid).reshape(-1),
        skin=tris if tris is not None else np.zeros((0, 3), int),
        fixed=fixed,
        nipple=nipple,
        frame=frame,
        tissue_label=None if tl is None else np.asarray(tl).reshape(-1),
        meta=meta,
    )
