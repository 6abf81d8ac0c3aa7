"""Conforming tetrahedral meshing of nested closed surfaces with gmsh.

The outer breast surface and the tumour surfaces (isotropically remeshed and checked
triangle meshes whose edge length already matches the element size,
:mod:`regtrack.model.boundary`) are merged as discrete gmsh surfaces
and kept as the boundary mesh; the tissue volume is
the outer surface loop with one hole per tumour and every tumour is its own volume
bounded by the same surface loop, so tissue and tumours share the interface nodes.
Sizes come from a background field: ``h`` far from tumours, ``h_k`` on tumour ``k``,
growing linearly to ``h`` over ``refine_distance_mm`` (gmsh ``Distance`` + ``Threshold``).

gmsh can hang on large discrete surfaces, so every attempt runs in a child process
(``python -m regtrack.model.mesher IN OUT``) that is killed after ``timeout_s``.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from regtrack._gmsh import gmsh_session

log = logging.getLogger(__name__)

ALGORITHMS_3D = {"delaunay": 1, "netgen": 4, "hxt": 10}


@dataclass
class MeshRequest:
    """Everything one gmsh attempt needs (surfaces in mm)."""

    outer_verts: np.ndarray
    outer_faces: np.ndarray
    tumour_verts: list[np.ndarray]
    tumour_faces: list[np.ndarray]
    size_mm: float
    tumour_sizes_mm: list[float] = field(default_factory=list)
    refine_distance_mm: float = 15.0
    algorithm: str = "delaunay"
    threads: int = 2
    optimize_netgen: bool = True
    feature_angle_deg: float = 40.0

    def settings(self) -> dict:
        d = asdict(self)
        for k in ("outer_verts", "outer_faces", "tumour_verts", "tumour_faces"):
            d.pop(k)
        return d


@dataclass
class MeshResult:
    points: np.ndarray  # (N, 3) mm
    tets: np.ndarray  # (E, 4) 0-based
    tumour_id: np.ndarray  # (E,) 0 tissue, k tumour
    gamma: np.ndarray  # gmsh "gamma" quality per tet
    min_sj: np.ndarray  # gmsh "minSJ" per tet
    seconds: float


def _save_request(req: MeshRequest, path: Path) -> None:
    arrays = {"outer_verts": req.outer_verts, "outer_faces": req.outer_faces}
    for i, (v, f) in enumerate(zip(req.tumour_verts, req.tumour_faces)):
        arrays[f"tv{i}"] = v
        arrays[f"tf{i}"] = f
    settings = req.settings()
    settings["n_tumours"] = len(req.tumour_verts)
    arrays["settings"] = np.frombuffer(json.dumps(settings).encode(), dtype=np.uint8)
    np.savez(path, **arrays)


def _load_request(path: Path) -> MeshRequest:
    z = np.load(path)
    s = json.loads(bytes(z["settings"]).decode())
    n = s.pop("n_tumours")
    return MeshRequest(z["outer_verts"], z["outer_faces"], [z[f"tv{i}"] for i in range(n)],
                       [z[f"tf{i}"] for i in range(n)], **s)


def _add_stl(gmsh, path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    """Merge one closed triangle surface (written as binary STL) as a discrete surface.

    Zero-area triangles are dropped first (gmsh's classifier stalls on them).
    """
    import meshio

    p = np.asarray(verts, float)[faces]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    faces = faces[area2 > 1e-10 * max(area2.max(), 1e-300)]
    meshio.write(path, meshio.Mesh(np.asarray(verts, float), [("triangle", faces)]), binary=True)
    gmsh.merge(str(path))


def _owner_of_surfaces(gmsh, originals: list[np.ndarray]) -> dict[int, int]:
    """Map each classified surface tag to the original surface (0 outer, k tumour k)."""
    from scipy.spatial import cKDTree

    allv = np.concatenate(originals)
    owner = np.concatenate([np.full(len(v), i) for i, v in enumerate(originals)])
    tree = cKDTree(allv)
    out = {}
    for _, tag in gmsh.model.getEntities(2):
        _, coords, _ = gmsh.model.mesh.getNodes(2, tag, includeBoundary=True)
        pts = np.asarray(coords).reshape(-1, 3)
        if len(pts) == 0:
            continue
        _, idx = tree.query(pts[:: max(1, len(pts) // 50)])
        out[tag] = int(np.bincount(owner[idx]).argmax())
    return out


def mesh_in_process(req: MeshRequest) -> MeshResult:
    """Run one gmsh attempt in this process (use :func:`run_gmsh` for the guarded form)."""
    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="regtrack-stl-"))
    try:
        with gmsh_session(threads=req.threads) as gmsh:
            gmsh.model.add("breast")
            _add_stl(gmsh, work / "outer.stl", req.outer_verts, req.outer_faces)
            for k, (v, f) in enumerate(zip(req.tumour_verts, req.tumour_faces), start=1):
                _add_stl(gmsh, work / f"tumour{k}.stl", v, f)
            # each merged STL is one discrete surface: tag 1 outer, 1 + k tumour k; the volume
            # mesh is built on these triangles as they are (no re-parametrisation: gmsh's
            # createGeometry fails or stalls on marching-cubes surfaces with cut faces)
            groups = {o: [o + 1] for o in range(1 + len(req.tumour_verts))}
            loops = {o: gmsh.model.geo.addSurfaceLoop(tags) for o, tags in sorted(groups.items())}
            tumour_keys = [o for o in sorted(loops) if o > 0]
            vol_tissue = gmsh.model.geo.addVolume([loops[0]] + [loops[o] for o in tumour_keys])
            vol_tum = {o: gmsh.model.geo.addVolume([loops[o]]) for o in tumour_keys}
            gmsh.model.geo.synchronize()
            gmsh.model.addPhysicalGroup(3, [vol_tissue], 1)
            for o, v in vol_tum.items():
                gmsh.model.addPhysicalGroup(3, [v], 100 + o)
            _size_fields(gmsh, req, {o: groups[o] for o in tumour_keys})
            gmsh.option.setNumber("Mesh.Algorithm", 6)
            gmsh.option.setNumber("Mesh.Algorithm3D", ALGORITHMS_3D[req.algorithm])
            gmsh.option.setNumber("Mesh.Optimize", 1)
            gmsh.option.setNumber("Mesh.OptimizeNetgen", 1 if req.optimize_netgen else 0)
            gmsh.model.mesh.generate(3)
            return _extract(gmsh, vol_tissue, vol_tum, time.perf_counter() - t0)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _size_fields(gmsh, req: MeshRequest, tumour_surfs: dict[int, list[int]]) -> None:
    h = req.size_mm
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)
    gmsh.option.setNumber("Mesh.MeshSizeMin", min([h] + list(req.tumour_sizes_mm)) * 0.5)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    fld = gmsh.model.mesh.field
    thresholds = []
    for o, surfs in tumour_surfs.items():
        hk = req.tumour_sizes_mm[o - 1] if o - 1 < len(req.tumour_sizes_mm) else h
        if hk >= h:
            continue
        d = fld.add("Distance")
        fld.setNumbers(d, "SurfacesList", surfs)
        fld.setNumber(d, "Sampling", 30)
        t = fld.add("Threshold")
        fld.setNumber(t, "InField", d)
        fld.setNumber(t, "SizeMin", hk)
        fld.setNumber(t, "SizeMax", h)
        fld.setNumber(t, "DistMin", 0.0)
        fld.setNumber(t, "DistMax", req.refine_distance_mm)
        thresholds.append(t)
    c = fld.add("Constant")
    fld.setNumber(c, "VIn", h)
    m = fld.add("Min")
    fld.setNumbers(m, "FieldsList", thresholds + [c])
    fld.setAsBackgroundMesh(m)


def _extract(gmsh, vol_tissue: int, vol_tum: dict[int, int], seconds: float) -> MeshResult:
    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = np.asarray(coords).reshape(-1, 3)
    tags = np.asarray(tags, np.int64)
    lookup = np.full(tags.max() + 1, -1, np.int64)
    lookup[tags] = np.arange(len(tags))
    tets, tid, etags = [], [], []
    for o, vol in [(0, vol_tissue)] + sorted(vol_tum.items()):
        et, en = gmsh.model.mesh.getElementsByType(4, vol)
        en = np.asarray(en, np.int64).reshape(-1, 4)
        tets.append(lookup[en])
        tid.append(np.full(len(en), o, np.int64))
        etags.append(np.asarray(et, np.int64))
    et_all = np.concatenate(etags)
    gamma = np.asarray(gmsh.model.mesh.getElementQualities(et_all, "gamma"))
    minsj = np.asarray(gmsh.model.mesh.getElementQualities(et_all, "minSJ"))
    tets = np.concatenate(tets)
    used = np.unique(tets)
    remap = -np.ones(len(coords), np.int64)
    remap[used] = np.arange(len(used))
    return MeshResult(coords[used], remap[tets], np.concatenate(tid), gamma, minsj, seconds)


def run_gmsh(req: MeshRequest, *, timeout_s: float) -> MeshResult:
    """Run :func:`mesh_in_process` in a child Python process, killed after ``timeout_s``.

    Raises
    ------
    TimeoutError
        The attempt ran longer than ``timeout_s``.
    RuntimeError
        gmsh failed (its last message is in the exception text).
    """
    with tempfile.TemporaryDirectory(prefix="regtrack-gmsh-") as td:
        inp, out = Path(td) / "in.npz", Path(td) / "out.npz"
        _save_request(req, inp)
        cmd = [sys.executable, "-m", "regtrack.model.mesher", str(inp), str(out)]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"gmsh did not finish within {timeout_s:g} s") from None
        if proc.returncode != 0 or not out.exists():
            lines = [ln for ln in (proc.stderr or "").strip().splitlines() if ln.strip()]
            raise RuntimeError(lines[-1] if lines else f"gmsh child exited with code {proc.returncode}")
        z = np.load(out)
        return MeshResult(z["points"], z["tets"], z["tumour_id"], z["gamma"], z["min_sj"], float(z["seconds"]))


def _main(argv: list[str]) -> int:
    req = _load_request(Path(argv[0]))
    res = mesh_in_process(req)
    np.savez(argv[1], points=res.points, tets=res.tets, tumour_id=res.tumour_id, gamma=res.gamma,
             min_sj=res.min_sj, seconds=res.seconds)
    return 0


if __name__ == "__main__":  # pragma: no cover - child process entry point
    sys.exit(_main(sys.argv[1:]))
