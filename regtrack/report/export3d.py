"""3-D results for ParaView and 3D Slicer: the model, each compressed state, the lesion.

Written into the report folder (``regtrack run``):

* ``model.vtu``: the patient model as meshed from the prone MRI (tetrahedra with cell
  data ``region``: 1 tissue, 2 tumour; skin triangles ``region`` 3; point data ``fixed``,
  1 on chest-wall nodes);
* ``<view>/<view>_<k>_<step>.vtu``: the model after each step of the view's protocol
  (``k = 0`` the prone reference), points at their deformed positions and point data
  ``displacement`` (mm) from the prone reference, plus ``<view>/<view>.pvd``, the
  series ParaView opens as one time-dependent data set (time = step number);
* ``lesion.mrk.json``: a 3D Slicer point list (markups JSON schema 1.0.3) of the tumour
  centroid in the MRI, the nipple, and the tumour centroid in each compressed state.

Every coordinate is LPS, mm (the DICOM patient frame of the MRI): 3D Slicer reads ``.vtu``
models as LPS by default and the markups file says so, so both land on the MRI series
loaded from the same case.  The compressed states are in the same frame (the body as it
lies between the plates, with the chest wall where it was in the MRI).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from regtrack import _io

MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/Slicer/Slicer/main/Modules/Loadable/"
                  "Markups/Resources/Schema/markups-schema-v1.0.3.json#")


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-").lower() or "step"


def _write_vtu(path: Path, points_lps: np.ndarray, model, *, point_data: dict) -> Path:
    import meshio

    ntri = len(model.skin)
    mesh = meshio.Mesh(points_lps, [("tetra", model.tets), ("triangle", model.skin)],
                       point_data=point_data,
                       cell_data={"region": [np.asarray(model.region, np.int32),
                                             np.full(ntri, 3, np.int32)],
                                  "tumour_id": [np.asarray(model.tumour_id, np.int32),
                                                np.zeros(ntri, np.int32)]})
    with _io.atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")
    return path


def write_model_vtu(model, path: str | Path) -> Path:
    """The prone model in LPS mm (see the module docstring)."""
    return _write_vtu(Path(path), model.frame.to_patient(model.points), model,
                      point_data={"fixed": model.fixed.astype(np.int8)})


def write_pvd(path: str | Path, files: list[tuple[float, str]]) -> Path:
    """A ParaView collection: ``(time, file name relative to the .pvd)`` per state."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for t, name in files:
        ET.SubElement(coll, "DataSet", timestep=f"{t:g}", group="", part="0", file=name)
    ET.indent(root)
    return _io.write_text(path, '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode")
                          + "\n")


def write_view_series(model, view: str, states: list[tuple[str, np.ndarray]],
                      folder: str | Path) -> tuple[list[Path], Path]:
    """The prone reference and each ``(step name, displacement (N, 3) mm, model frame)``
    of ``view`` as VTU files and their ``.pvd`` series in ``folder``."""
    folder = Path(folder)
    stem = view.lower()
    axes = model.frame.axes
    x0 = model.frame.to_patient(model.points)
    files = [(0.0, f"{stem}_0_prone-reference.vtu", np.zeros_like(x0))]
    for k, (name, u) in enumerate(states, start=1):
        files.append((float(k), f"{stem}_{k}_{_slug(name)}.vtu", np.asarray(u, float) @ axes))
    paths = [_write_vtu(folder / name, x0 + u, model,
                        point_data={"displacement": u, "fixed": model.fixed.astype(np.int8)})
             for _, name, u in files]
    pvd = write_pvd(folder / f"{stem}.pvd", [(t, name) for t, name, _ in files])
    return paths, pvd


def tumour_centroid(model, positions: np.ndarray | None = None) -> np.ndarray | None:
    """Volume-weighted centroid (mm, model frame) of the tumour elements at ``positions``
    (default: the reference), or None without a tumour."""
    x = model.points if positions is None else np.asarray(positions, float)
    sel = np.asarray(model.region) == 2
    if not sel.any():
        return None
    vol = np.abs(model.tet_volumes(x))[sel]
    centres = x[model.tets[sel]].mean(axis=1)
    return (centres * vol[:, None]).sum(axis=0) / vol.sum()


def markups_document(points: list[tuple[str, np.ndarray, str]]) -> dict:
    """A 3D Slicer markups point list (LPS, mm) of ``(label, position, description)``."""
    ctrl = [{"id": str(k), "label": label, "description": desc, "associatedNodeID": "",
             "position": [float(c) for c in pos], "orientation": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0,
                                                                   0.0, 0.0, 1.0],
             "selected": True, "locked": True, "visibility": True, "positionStatus": "defined"}
            for k, (label, pos, desc) in enumerate(points, start=1)]
    return {"@schema": MARKUPS_SCHEMA,
            "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                         "locked": True, "labelFormat": "%N-%d", "controlPoints": ctrl,
                         "measurements": [],
                         "display": {"visibility": True, "opacity": 1.0,
                                     "color": [0.9, 0.2, 0.2], "selectedColor": [0.9, 0.2, 0.2],
                                     "glyphType": "Sphere3D", "glyphScale": 3.0,
                                     "textScale": 3.0}}]}


def write_markups(path: str | Path, points: list[tuple[str, np.ndarray, str]]) -> Path:
    """Write :func:`markups_document` as ``path`` (``.mrk.json``)."""
    return _io.write_json(path, markups_document(points))


def write_3d_outputs(model, states: dict[str, list[tuple[str, np.ndarray]]], out: str | Path, *,
                     lesion_lps: np.ndarray | None = None, lesion_label: str = "tumour (MRI)"
                     ) -> list[Path]:
    """``model.vtu``, each view's series and ``lesion.mrk.json`` in ``out`` (see the module
    docstring); ``states``: per view the ``(step name, displacement)`` list; ``lesion_lps``:
    the tracked lesion in the MRI (default: the tumour centroid of the model)."""
    out = Path(out)
    paths = [write_model_vtu(model, out / "model.vtu")]
    points: list[tuple[str, np.ndarray, str]] = []
    c0 = tumour_centroid(model)
    if lesion_lps is None and c0 is not None:
        lesion_lps = model.frame.to_patient(c0)
    if lesion_lps is not None:
        points.append((lesion_label, np.asarray(lesion_lps, float), "prone MRI"))
    points.append(("nipple (MRI)", model.frame.origin, "prone MRI, model origin"))
    for view, steps in states.items():
        vtus, pvd = write_view_series(model, view, steps, out / view.lower())
        paths += [*vtus, pvd]
        if steps and c0 is not None:
            c = tumour_centroid(model, model.points + np.asarray(steps[-1][1], float))
            points.append((f"tumour ({view} compressed)", model.frame.to_patient(c),
                           f"after '{steps[-1][0]}', same frame as {view.lower()}.pvd"))
    if len(points) > 1 or lesion_lps is not None:
        paths.append(write_markups(out / "lesion.mrk.json", points))
    return paths
