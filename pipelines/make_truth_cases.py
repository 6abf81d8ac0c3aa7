"""Ground-truth mammography cases from Pelicano exams, made with a solver that is not ours.

Issue 52, item 4: an independent development cohort.  For each exam and breast this
script builds, *without regtrack's model, mechanics or virtual-mammogram stages*:

1. **Its own mesh.**  The breast region is the anatomical selection regtrack makes
   (chest-wall plane, inframammary fold, midline; see :func:`breast_geometry` for why),
   smoothed and resampled to 2 mm, marching cubes (scikit-image), gmsh re-meshing of that
   surface (or, where gmsh cannot, an isotropic remeshing filled as it is) and a tet10
   volume mesh (straight-sided second order, C3D10) at an element size chosen for about
   ``--target-tets`` elements (a few thousand nodes; twice as many for a view CalculiX
   cannot finish on it); the tissue class of each element is the *detailed* label at its
   centroid.
2. **A CalculiX 2.20 compression** per view (``ccx``, single-threaded): heterogeneous
   neo-Hookean tissue (``*HYPERELASTIC, NEO HOOKE``; fat labels 5-7 and skin, gland 1-3,
   transition 4 = mean, tumour -3/-4 = 10 x gland; c1 drawn per case); chest-wall nodes
   (the cut plane and next to the muscle) held in the plate plane and free along the
   plate normal (fully fixed, the plates pinched the base and CalculiX diverged at first
   contact); the prone MRI's gravity unloaded and standing gravity applied from the MRI
   shape (``*DLOAD GRAV`` along ``d_standing - d_prone``, rho = 1000 kg/m^3), ramped in
   with the breast held half-way compressed (``T_G0``, ``T_G1``, ``HOLD``); two rigid
   plates (``*RIGID BODY`` on one layer of C3D8 elements) with surface-to-surface penalty
   contact and ``*FRICTION`` mu drawn in 0.05-0.2; the lower plate overlaps the breast's
   lowest point by 0.5 mm (no free mode along the normal), the upper plate moves down
   until the gap is (1 - D) times the uncompressed thickness, D drawn in 0.30-0.50 (a run
   that stops after at least ``T_ACCEPT`` of the plate travel, the upper plate pressing
   on the breast, is kept at its last converged increment, and the gap reached is the one
   written to the DICOM); MLO:
   plates rotated about the antero-posterior axis by an angle drawn in 40-60 deg, gravity
   first on the breast clamped at the wall, the chest-wall nodes then squeezed along the
   plate normal with the plates (instead of free along it), and the torso a rigid plane
   in frictionless contact behind the breast (:func:`write_ccx`, docs/truth-cases.md).
3. **A cone-beam rendering** (point source SID 650-660 mm above the detector, detector
   15-25 mm below the lower plate, the source's foot at the middle of the chest-wall edge)
   of fat / gland / tumour path lengths through the 8 linear sub-tets of every tet10
   (``regtrack.virtual.xray.path_lengths``, a geometric helper), Poisson noise, a random
   in-plane rotation (-10..10 deg) about the projected nipple, written as DICOM MG
   (``regtrack.phantom.dicom_mg.write_mg_dicom``) with BodyPartThickness, CompressionForce
   (N), PositionerPrimaryAngle (MLO), DistanceSourceToDetector, DistanceSourceToPatient,
   EstimatedRadiographicMagnificationFactor and ImagerPixelSpacing.

Frames.  The plate frame of a view is :func:`regtrack.virtual.frames.plate_frame` (a
*convention*: which way CC and MLO plates and images are oriented, shared by every
mammography unit), applied to the model frame (origin nipple, x anterior, y superior,
z patient right).  The image is the canonical frame of :mod:`regtrack.views` (chest wall
left), stored under the IHE hanging (right breasts flipped).  The in-plane rotation is
``q = R(theta) (p' - n') + n'`` with ``R = [[c, -s], [s, c]]`` (y down), ``p'`` the
cone-beam projection on the detector and ``n'`` the projected nipple: the sense of
regtrack's ``theta_p``.  An unrotated copy (theta = 0) of every case is written too, for
the frame check.

Output (all under ``--out``, default reports/truth)::

    work/<case>/            mesh, CalculiX decks and logs, displacements (npz)
    cases/<case>_track/     case.toml: label map + DICOMs, no tumour outline (tracking mode)
    cases/<case>_paper/     the same DICOMs + the true tumour outline (paper mode)
    cases/<case>_paper_rot0/  unrotated DICOMs + outline (frame check)
    truth/<case>.json       the hidden truth (outside every case folder)

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python pipelines/make_truth_cases.py --exams 03R,10R
        [--views CC,MLO] [--out reports/truth] [--target-tets 1200]

Data: Pelicano et al., Sensors 2021 and PLoS One 2024 (../shared/data/pelicano).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from regtrack._gmsh import gmsh_session

log = logging.getLogger("make_truth_cases")
REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("REGTRACK_SHARED_DATA", REPO.parent / "shared" / "data")) / "pelicano"

FAT, GLAND, TRANS, TUM = 0, 1, 2, 3
GROUP_NAMES = {FAT: "fat", GLAND: "gland", TRANS: "transition", TUM: "tumour"}
#: attenuation (1/mm, ~20 keV; Johns & Yaffe 1987)
MU = {FAT: 0.0456, GLAND: 0.0802, TRANS: 0.0629, TUM: 0.0844}
RHO_KG_MM3 = 1.0e-6          # 1000 kg/m^3 in kg/mm^3 (units mm, mN, kPa = mN/mm^2, kg, s)
G_MM_S2 = 9810.0
PIXEL_MM = 0.1
#: contact penalty (kPa/mm) and friction stick slope (kPa/mm): soft tissue, c1 < 2 kPa
PENALTY = 20.0
STICK_SLOPE = 5.0
#: schedule of the single CalculiX step (pseudo-time 0-1): the upper plate travels HOLD of
#: the way over 0-T_G0, stays while gravity ramps in over T_G0-T_G1, then travels the rest
#: over T_G1-1 with gravity on.  A soft breast hanging free under gravity drops and sags
#: tens of mm onto a tilted plate, and CalculiX's Newton did not converge through it
#: (MLO: 2 of 3 exams); held between the plates first, as a technologist holds the breast
#: while the paddle comes down, it did.  On a CC the order hardly matters: gravity first on
#: the free breast (T_G0 = 0, T_G1 = 0.2, HOLD = 0) gave exam 29 R the same plate force and
#: regtrack the same tracking error within 0.04 mm (docs/truth-cases.md).
T_G0, T_G1, HOLD = 0.4, 0.6, 0.5
#: the MLO's schedule: gravity first (over 0-T_G1_MLO, the plates still), then the whole
#: plate travel.  Held half-way first (the CC schedule), the MLO diverged at the first
#: increments of gravity on every set-up tried (docs/truth-cases.md); with the chest-wall
#: section squeezed with the plates (write_ccx), which carries the breast's weight, the
#: free-hanging start converged on the exams tried.
T_G0_MLO, T_G1_MLO, HOLD_MLO = 0.0, 0.2, 0.0
#: the torso behind the MLO's breast: a rigid plane at the chest wall (the most posterior
#: node), frictionless contact with the breast's free surface, as wide as the plates and
#: this much (mm) beyond both plates along their normal
TORSO_MARGIN_MM = 40.0
#: largest increment of the step (pseudo-time); a run that fails is run once more with the
#: second value, in either view (the MLOs of 05 R and 49 R then passed the gravity ramp
#: where they had failed, and the CC of 09 R reached 88 % of the travel instead of 58 %)
MAX_INCREMENT = 0.03
RETRY_MAX_INCREMENT = 0.01
#: address-space cap of one CalculiX process (GiB); a few thousand tet10 need well under 1
CCX_MEMORY_GB = 4
#: Gaussian smoothing (voxels) of the breast mask before marching cubes, tried in order,
#: and the time one gmsh attempt may take (a good surface meshes in about 10 s)
SMOOTHING_VOXELS = (1.0, 2.0, 3.0)
GMSH_TIMEOUT_S = 120.0
#: when gmsh cannot re-parametrise any of them: each surface again, remeshed isotropically
#: with edges of this fraction of the element size (gmsh's smallest element on the
#: re-parametrised path) and filled as it is, as regtrack's own mesher does (02 L, 12 R,
#: 27 R at sigma 1; 47 L's sigma-1 surface folds through itself when remeshed, sigma 2
#: does not)
REMESH_EDGE = 0.6
#: a view that CalculiX cannot finish at either increment is run again on a mesh of REFINE
#: times the elements, up to REFINE_LEVELS times: a closer discretisation of the same
#: problem, for failures that are single exploding Newton iterates (docs/truth-cases.md).
#: 05 R's MLO failed at 95 % of gravity with the increment 0.03 at both sizes; with 0.01
#: it reached 67 % of the travel at 1,200 target elements when a 900 s limit stopped it on
#: a loaded host, and finished at 2,400 in 489 s
REFINE = 2.0
REFINE_LEVELS = 1
#: a CalculiX run that stops early is kept at its last converged increment when the upper
#: plate has travelled at least this fraction of the way to the drawn gap
T_ACCEPT = 0.7
#: ... and presses on the breast with at least this force (mN): a plate that has not
#: touched it (19 L's MLO stopped at 74 % of the travel with 0 N) images no compression
MIN_CONTACT_MN = 1.0
#: initial overlap of the lowest breast point with the lower plate (removes the free mode
#: along the plate normal; the chest wall holds the breast in-plane only, see write_ccx)
OVERLAP_MM = 0.5
#: the nipple is the centre of the skin cap this deep below the breast's apex along the
#: chest-wall normal, on the 2 mm surface (the definition of regtrack's
#: ``[model] nipple_depth_mm``): the label maps have no nipple, and the most anterior node
#: of a mesh of 13-22 mm elements, the first definition, lay 2.3-8.5 mm from that apex on
#: the eight exams of docs/truth-cases.md
NIPPLE_CAP_MM = 3.0
RENDER_MM = 0.4
#: gmsh tet10 node order -> Abaqus/CalculiX C3D10 (edges 01,12,20,03,13,23)
C3D10_EDGES = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
C3D10_FACES = {1: (0, 1, 2), 2: (0, 3, 1), 3: (1, 3, 2), 4: (2, 3, 0)}
#: the 8 linear sub-tets of a C3D10 (4 corner tets, the inner octahedron split along 4-9)
SUBTETS = np.array([[0, 4, 6, 7], [4, 1, 5, 8], [6, 5, 2, 9], [7, 8, 9, 3],
                    [4, 9, 5, 6], [4, 9, 6, 7], [4, 9, 7, 8], [4, 9, 8, 5]])


# ------------------------------------------------------------------------- parameters

def draw_params(exam: str, side: str, seed: int) -> dict:
    """The case's hidden parameters (seeded by exam, side and --seed)."""
    rng = np.random.default_rng([seed, int(exam), 0 if side == "R" else 1])
    fat = float(rng.uniform(0.3, 0.6))
    gland = float(rng.uniform(0.8, 1.6))
    p = {
        "c1_kpa": {"fat": fat, "gland": gland, "transition": 0.5 * (fat + gland), "tumour": 10.0 * gland},
        "nu": 0.49,
        "friction": float(rng.uniform(0.05, 0.2)),
        "D": {"CC": float(rng.uniform(0.30, 0.50)), "MLO": float(rng.uniform(0.30, 0.50))},
        "mlo_angle_deg": float(rng.uniform(40.0, 60.0)),
        "rotation_deg": {"CC": float(rng.uniform(-10, 10)), "MLO": float(rng.uniform(-10, 10))},
        "sid_mm": float(rng.uniform(650.0, 660.0)),
        "detector_gap_mm": {"CC": float(rng.uniform(15.0, 25.0)), "MLO": float(rng.uniform(15.0, 25.0))},
        "pixel_mm": PIXEL_MM,
        "quanta_per_pixel": 20000.0,
        "noise_seed": int(rng.integers(0, 2**31 - 1)),
    }
    return p


# ------------------------------------------------------------------------- label map

def find_zip(exam: str, kind: str) -> Path:
    d = DATA / f"Exam_{exam}"
    for f in d.iterdir():
        if f.name.lower() == f"label_map_{kind}.zip":
            return f
    raise FileNotFoundError(f"{d}: no label_map_{kind}.zip")


def model_basis(side: str, normal_lps=None) -> np.ndarray:
    """Rows: model axes in LPS: x the chest-wall plane's normal (anterior, in the axial
    plane), y superior, z = x cross y (patient right when x is anterior)."""
    x = np.array([0.0, -1.0, 0.0]) if normal_lps is None else np.asarray(normal_lps, float)
    x = np.array([x[0], x[1], 0.0]) / np.hypot(x[0], x[1])  # its axial component
    y = np.array([0.0, 0.0, 1.0])
    return np.stack([x, y, np.cross(x, y)])


def breast_geometry(exam: str, side: str) -> dict:
    """Breast mask, chest-wall plane and tumour components (LPS mm) of one exam's breast.

    The breast *region* (which voxels are breast: the chest-wall plane, the inframammary
    fold and the midline) is regtrack's anatomical selection
    (:func:`regtrack.model.prepare.prepare_breast` on the simple map at its defaults).
    How far the breast reaches is set by the patient's anatomy and the technologist's
    positioning, which neither model knows; two different crop rules would measure each
    other, not the mechanics or the registration.  Everything after the region (the detailed
    labels, the mesh, the materials, the boundary conditions, the solver) is the truth's own.
    """
    from regtrack.imaging.readers import read_label_map
    from regtrack.model.config import MeshConfig
    from regtrack.model.labels import get_scheme
    from regtrack.model.prepare import prepare_breast

    vol = read_label_map(find_zip(exam, "detailed"))
    lab = vol.data
    A = np.asarray(vol.affine, float)
    prep = prepare_breast(read_label_map(find_zip(exam, "simple")),
                          scheme=get_scheme("pelicano-simple"), config=MeshConfig(), side=side)
    # regtrack's breast voxels (its LPS-reoriented crop) on the detailed map's grid
    Ac = np.asarray(prep.volume.affine, float)
    M = np.linalg.inv(Ac[:3, :3]) @ A[:3, :3]
    t = np.linalg.inv(Ac[:3, :3]) @ (A[:3, 3] - Ac[:3, 3])
    ijk = np.indices(lab.shape, dtype=np.float32).reshape(3, -1)
    ic = np.rint(M.astype(np.float32) @ ijk + t[:, None].astype(np.float32)).astype(np.int64)
    del ijk
    ok = np.all((ic >= 0) & (ic < np.array(prep.breast.shape)[:, None]), axis=0)
    mask = np.zeros(ic.shape[1], bool)
    mask[ok] = prep.breast[ic[0, ok], ic[1, ok], ic[2, ok]]
    mask = mask.reshape(lab.shape)
    del ic, ok
    if not mask.any():
        raise RuntimeError(f"exam {exam} {side}: empty breast mask")
    cw = prep.chest_wall.plane
    # tumour components inside the breast (>= 20 voxels)
    tum = np.isin(lab, [-3, -4]) & mask
    tl, tn = ndimage.label(tum)
    tumours = []
    vox_vol = abs(np.linalg.det(A[:3, :3]))
    for k in range(1, tn + 1):
        sel = tl == k
        nv = int(sel.sum())
        if nv < 20:
            continue
        surf = sel & ~ndimage.binary_erosion(sel)
        idx = np.argwhere(surf)
        pts = idx @ A[:3, :3].T + A[:3, 3]
        cen = np.argwhere(sel).mean(0) @ A[:3, :3].T + A[:3, 3]
        vals, cnt = np.unique(lab[sel], return_counts=True)
        tumours.append({"voxels": nv, "volume_mm3": nv * vox_vol, "centroid_lps_mm": cen.tolist(),
                        "label": int(vals[np.argmax(cnt)]), "surface_points_lps": pts})
    tumours.sort(key=lambda t: -t["voxels"])
    # muscle distance (mm) for the chest-wall nodes
    sp = np.linalg.norm(A[:3, :3], axis=0)
    dist_muscle = ndimage.distance_transform_edt(~(lab == -1), sampling=sp).astype(np.float32)
    return {"labels": lab, "affine": A, "mask": mask, "cut_ant_mm": 0.0, "tumours": tumours,
            "plane": {"normal_lps": np.asarray(cw.normal, float), "offset_mm": float(cw.offset)},
            "dist_muscle": dist_muscle, "spacing": sp}


def lps_to_index(A: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return (np.asarray(pts, float) - A[:3, 3]) @ np.linalg.inv(A[:3, :3]).T


# ------------------------------------------------------------------------- meshing

def surface_from_mask(geo: dict, step_mm: float = 2.0,
                      sigma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface (LPS mm) of the smoothed breast mask resampled to step_mm."""
    from skimage import measure

    mask, A = geo["mask"], geo["affine"]
    sl = ndimage.find_objects(mask.astype(np.int8))[0]
    sl = tuple(slice(max(s.start - 4, 0), s.stop + 4) for s in sl)
    sub = mask[sl].astype(np.float32)
    sp = geo["spacing"]
    f = np.maximum(1, np.round(step_mm / sp)).astype(int)
    sm = ndimage.gaussian_filter(sub, sigma=sigma)
    co = sm[::f[0], ::f[1], ::f[2]]
    co = np.pad(co, 1)
    verts, faces, _, _ = measure.marching_cubes(co, 0.5)
    idx = (verts - 1) * f + np.array([s.start for s in sl])
    pts = idx @ A[:3, :3].T + A[:3, 3]
    return pts, faces


def remeshed_surface(pts: np.ndarray, faces: np.ndarray, size_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The marching-cubes surface remeshed isotropically (pymeshlab, edges ``REMESH_EDGE``
    of the element size), its enclosed volume restored (the chords of long edges cut the
    curvature: -5.6 to -9.2 % on Pelicano 02 L, 05 R, 12 R, 27 R, 47 L at edges of 0.8 of
    the element size)."""
    from regtrack.model.remesh import remesh, restore_volume
    from regtrack.model.surfaces import Surface

    mc = Surface(np.asarray(pts, float), np.asarray(faces, np.int64))
    out = restore_volume(remesh(mc, edge_mm=REMESH_EDGE * size_mm), abs(mc.volume))
    return out.verts, out.faces


def gmsh_tet10_timed(pts: np.ndarray, faces: np.ndarray, size_mm: float,
                     timeout_s: float, **kw) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gmsh_tet10` (keywords ``kw``) in a forked process, stopped after
    ``timeout_s`` (gmsh's 3-D Delaunay can loop on a bad surface instead of failing)."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    q = ctx.Queue()

    def work():
        try:
            q.put(("ok", gmsh_tet10(pts, faces, size_mm, **kw)))
        except Exception as e:  # noqa: BLE001 - reported to the parent
            q.put(("error", str(e)))

    pr = ctx.Process(target=work, daemon=True)
    pr.start()
    try:
        kind, val = q.get(timeout=timeout_s)
    except Exception:  # queue.Empty: gmsh still running
        pr.kill()
        raise RuntimeError(f"gmsh did not finish in {timeout_s:.0f} s") from None
    pr.join()
    if kind == "error":
        raise RuntimeError(val)
    return val


def gmsh_tet10(pts: np.ndarray, faces: np.ndarray, size_mm: float, *,
               reparametrise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """gmsh: fill the surface with straight-sided tet10 (C3D10 order).  ``reparametrise``:
    gmsh re-meshes the surface first (classify, create its geometry, mesh it at the
    size); otherwise the volume is built on the given triangles as they are."""
    with gmsh_session(threads=1) as gmsh:
        gmsh.model.add("breast")
        s = gmsh.model.addDiscreteEntity(2)
        tags = np.arange(1, len(pts) + 1)
        gmsh.model.mesh.addNodes(2, s, tags.tolist(), pts.ravel().tolist())
        gmsh.model.mesh.addElementsByType(s, 2, [], (faces + 1).ravel().tolist())
        gmsh.model.mesh.removeDuplicateNodes()
        if reparametrise:
            gmsh.model.mesh.classifySurfaces(np.deg2rad(50), True, True, np.deg2rad(180))
            gmsh.model.mesh.createGeometry()
        surfs = [e[1] for e in gmsh.model.getEntities(2)]
        loop = gmsh.model.geo.addSurfaceLoop(surfs)
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.6 * size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.SecondOrderLinear", 1)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        ntag, ncoord, _ = gmsh.model.mesh.getNodes()
        coords = np.asarray(ncoord).reshape(-1, 3)
        et, en = gmsh.model.mesh.getElementsByType(11)
        conn = np.asarray(en, np.int64).reshape(-1, 10)
    if not len(conn):  # gmsh can return a surface with no volume mesh without an error
        raise RuntimeError("gmsh made no tetrahedra")
    # compact node numbering
    order = np.argsort(ntag)
    ntag = np.asarray(ntag)[order]
    coords = coords[order]
    used = np.unique(conn)
    pos = np.searchsorted(ntag, used)
    nodes = coords[pos]
    conn = np.searchsorted(used, conn)
    # reorder the mid-side nodes to C3D10 by midpoint matching (robust to gmsh's order)
    c = nodes[conn[:, :4]]
    out = np.empty_like(conn)
    out[:, :4] = conn[:, :4]
    for k, (a, b) in enumerate(C3D10_EDGES):
        mid = 0.5 * (c[:, a] + c[:, b])
        d = np.linalg.norm(nodes[conn[:, 4:]] - mid[:, None, :], axis=2)
        out[:, 4 + k] = conn[np.arange(len(conn)), 4 + np.argmin(d, axis=1)]
    # positive volume in the (right-handed) model frame is checked later
    return nodes, out


def tet_volumes(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = x[tets[:, :4]]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def fix_orientation(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    v = tet_volumes(x, tets)
    neg = v < 0
    if neg.any():  # swap corners 1<->2 and the affected edges: 01<->02(=20), 13<->23
        t = tets[neg].copy()
        t[:, [1, 2]] = t[:, [2, 1]]
        t[:, [4, 6]] = t[:, [6, 4]]
        t[:, [8, 9]] = t[:, [9, 8]]
        tets = tets.copy()
        tets[neg] = t
    return tets


def boundary_faces(tets: np.ndarray) -> list[tuple[int, int, tuple[int, int, int]]]:
    """(element index, C3D10 face id, corner nodes) of faces used once."""
    rec = {}
    for fid, (a, b, c) in C3D10_FACES.items():
        f = np.sort(tets[:, [a, b, c]], axis=1)
        for e in range(len(tets)):
            key = tuple(f[e])
            rec.setdefault(key, []).append((e, fid))
    out = []
    for key, lst in rec.items():
        if len(lst) == 1:
            out.append((lst[0][0], lst[0][1], key))
    return out


def build_mesh(geo: dict, side: str, target_tets: int, origin_lps: np.ndarray | None = None) -> dict:
    """The truth's tet10 mesh of about ``target_tets`` elements in the model frame (origin
    the nipple: the apex of the smooth surface, or ``origin_lps`` when given, so that a
    finer mesh of the same breast keeps the same material point)."""
    from regtrack.model.geometry import detect_nipple

    vol_mm3 = float(geo["mask"].sum() * np.prod(geo["spacing"]))
    size = float((vol_mm3 / target_tets * 6 * np.sqrt(2)) ** (1 / 3))
    t0 = time.perf_counter()
    # gmsh rejects some marching-cubes surfaces (overlapping facets, thin folds); a
    # smoother mask is the retry, then the same surfaces remeshed isotropically and filled
    # as they are, the same for every exam
    attempts = [(sigma, True) for sigma in SMOOTHING_VOXELS] + [(sigma, False) for sigma in SMOOTHING_VOXELS]
    labels = [f"smoothed with sigma {sigma:g} voxels, " + ("re-parametrised by gmsh" if reparam else
                                                          f"remeshed (edges {REMESH_EDGE * size:.1f} mm)")
              for sigma, reparam in attempts]
    for k, (sigma, reparametrise) in enumerate(attempts):
        pts, faces = surface_from_mask(geo, sigma=sigma)
        surface = labels[k]
        try:
            sv, sf = (pts, faces) if reparametrise else remeshed_surface(pts, faces, size)
            nodes_lps, tets = gmsh_tet10_timed(sv, sf, size, GMSH_TIMEOUT_S, reparametrise=reparametrise)
            break
        except RuntimeError as e:  # gmsh_tet10_timed: a gmsh error or its timeout
            if k == len(attempts) - 1:
                raise
            log.warning("gmsh failed on the surface %s (%s); next: %s", surface, e, labels[k + 1])
    if not reparametrise:
        log.info("meshed on the surface %s", surface)
    B = model_basis(side, geo["plane"]["normal_lps"])
    # nipple (the model frame's origin): the apex of the smooth breast surface along the
    # chest-wall normal, the centre of its NIPPLE_CAP_MM cap; a material point, not a node.
    # The surface is the one meshed: a remeshed surface's long edges cut a nipple bump of
    # the marching-cubes surface away, and its apex would lie outside the mesh (8 mm on 27 R)
    if origin_lps is None:
        origin_lps = detect_nipple(sv, B[0], depth_mm=NIPPLE_CAP_MM)
    x = (nodes_lps - origin_lps) @ B.T
    tets = fix_orientation(x, tets)
    vol = tet_volumes(x, tets)
    # tissue group per element from the detailed labels at the centroid
    A, lab = geo["affine"], geo["labels"]
    cen = nodes_lps[tets[:, :4]].mean(1)
    ijk = np.clip(np.round(lps_to_index(A, cen)).astype(int), 0, np.array(lab.shape) - 1)
    lv = lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    grp = np.full(len(tets), FAT, np.int64)
    grp[np.isin(lv, [1, 2, 3])] = GLAND
    grp[lv == 4] = TRANS
    grp[np.isin(lv, [-3, -4])] = TUM
    # chest-wall nodes: on the cut plane or next to the muscle
    pl = geo["plane"]
    ant = nodes_lps @ pl["normal_lps"] - pl["offset_mm"]  # distance anterior of the chest-wall plane
    ijn = np.clip(np.round(lps_to_index(A, nodes_lps)).astype(int), 0, np.array(lab.shape) - 1)
    dm = geo["dist_muscle"][ijn[:, 0], ijn[:, 1], ijn[:, 2]]
    on_cut = ant < geo["cut_ant_mm"] + 2.5
    fixed = on_cut | (dm < 2.5)
    corner = np.zeros(len(x), bool)
    corner[np.unique(tets[:, :4])] = True
    return {"x": x, "tets": tets, "group": grp, "fixed": fixed, "on_cut": on_cut,
            "origin_lps": origin_lps, "basis": B, "element_size_mm": size, "surface": surface,
            "mesher_s": time.perf_counter() - t0,
            "n_nodes": int(len(x)), "n_tets": int(len(tets)), "min_vol": float(vol.min()),
            "volume_mm3": float(vol.sum()), "corner": corner,
            "group_volume_mm3": {GROUP_NAMES[g]: float(vol[grp == g].sum()) for g in GROUP_NAMES}}


# ------------------------------------------------------------------------- CalculiX

def solver_frame(view: str, side: str, angle: float | None):
    """Right-handed solver basis (rows e_x, s*e_down, n) and s (Y sign back to regtrack's)."""
    from regtrack.virtual.frames import plate_frame

    pf = plate_frame(view, side, angle_deg=angle)
    s = 1.0 if np.dot(np.cross(pf.e_x, pf.e_down), pf.normal) > 0 else -1.0
    return np.stack([pf.e_x, s * pf.e_down, pf.normal]), s, pf


def plate_block(x0, x1, y0, y1, z, thick, nx, ny, node0, elem0, up: bool, axes=(0, 1, 2)):
    """One layer of C3D8 over [x0,x1]x[y0,y1]; contact face at height z (facing +z if up).
    ``axes``: the solver axes of the layer's (x, y, z), a cyclic permutation (right-handed):
    ``(1, 2, 0)`` lays it over y and z with its height along X (the torso)."""
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    zs = (z - thick, z) if up else (z, z + thick)
    nodes, nid = {}, node0
    lines = []
    for k, zz in enumerate(zs):
        for j, yy in enumerate(ys):
            for i, xx in enumerate(xs):
                nodes[(i, j, k)] = nid
                c = [0.0, 0.0, 0.0]
                c[axes[0]], c[axes[1]], c[axes[2]] = xx, yy, zz
                lines.append(f"{nid}, {c[0]:.6f}, {c[1]:.6f}, {c[2]:.6f}")
                nid += 1
    elems, eid = [], elem0
    for j in range(ny):
        for i in range(nx):
            n = [nodes[(i, j, 0)], nodes[(i + 1, j, 0)], nodes[(i + 1, j + 1, 0)], nodes[(i, j + 1, 0)],
                 nodes[(i, j, 1)], nodes[(i + 1, j, 1)], nodes[(i + 1, j + 1, 1)], nodes[(i, j + 1, 1)]]
            elems.append((eid, n))
            eid += 1
    face = "S2" if up else "S1"  # S2 = top (5-8), S1 = bottom (1-4)
    return lines, elems, face, nid, eid


def body_force_direction(basis: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit direction (model frame) and magnitude (in g) of the truth's body force
    ``g (d_standing - d_prone)``: the prone MRI's gravity (LPS anterior) unloaded and
    standing gravity (model -y, caudal) applied, both from the MRI shape."""
    d_prone = np.asarray(basis, float) @ np.array([0.0, -1.0, 0.0])
    g = np.array([0.0, -1.0, 0.0]) - d_prone
    scale = float(np.linalg.norm(g))
    return g / scale, scale


def schedule(view: str) -> tuple[float, float, float]:
    """(T_G0, T_G1, HOLD) of a view's CalculiX step."""
    return (T_G0_MLO, T_G1_MLO, HOLD_MLO) if view == "MLO" else (T_G0, T_G1, HOLD)


def write_ccx(path: Path, mesh: dict, view: str, side: str, p: dict,
              max_increment: float = MAX_INCREMENT) -> dict:
    """The CalculiX deck of one view.

    MLO only (the CC deck is unchanged): the torso is a rigid plane at the chest wall
    (frictionless contact with the breast's free surface); the chest-wall nodes are squeezed
    along the plates' normal with the plates, each moved by the plate travel times its
    height above the lower plate over the upper plate's, instead of free along the normal
    (free, the breast's weight along the oblique normal, 0.8 g, had nothing but the lower
    plate to rest on); gravity comes first (:func:`schedule`)."""
    angle = p["mlo_angle_deg"] if view == "MLO" else 0.0
    mlo = view == "MLO"
    t_g0, t_g1, hold = schedule(view)
    Bs, s, pf = solver_frame(view, side, angle)
    xs = mesh["x"] @ Bs.T            # solver coordinates (X, s*Y, h), origin nipple
    h0 = float(xs[:, 2].min())
    xs[:, 2] -= h0 + OVERLAP_MM      # lower plate contact face at h = 0, OVERLAP_MM into the breast
    T0 = float(xs[:, 2].max()) + OVERLAP_MM
    gap = (1.0 - p["D"][view]) * T0
    upper0 = T0 + 1.0
    g_model, g_scale = body_force_direction(mesh["basis"])
    g = Bs @ g_model
    tets, grp = mesh["tets"], mesh["group"]
    nn = len(xs)
    lo, hi = xs[:, :2].min(0) - 25.0, xs[:, :2].max(0) + 25.0
    ext = hi - lo
    nx, ny = max(4, int(ext[0] // 12)), max(4, int(ext[1] // 12))
    L1, E1, f1, nid, eid = plate_block(lo[0], hi[0], lo[1], hi[1], 0.0, 2.0, nx, ny, nn + 1, len(tets) + 1, True)
    L2, E2, f2, nid, eid = plate_block(lo[0], hi[0], lo[1], hi[1], upper0, 2.0, nx, ny, nid, eid, False)
    if mlo:  # the torso: a rigid slab behind the chest wall, facing the breast
        xw = float(xs[:, 0].min())
        zlo, zhi = -TORSO_MARGIN_MM, upper0 + TORSO_MARGIN_MM
        nz = max(4, int((zhi - zlo) // 12))
        LW, EW, _, nid, eid = plate_block(lo[1], hi[1], zlo, zhi, xw, 2.0, ny, nz, nid, eid, True,
                                          axes=(1, 2, 0))
    r = list(range(nid, nid + (6 if mlo else 4)))
    out = ["*HEADING", f"regtrack truth (CalculiX) {view}", "*NODE, NSET=NALL"]
    out += [f"{i + 1}, {a:.6f}, {b:.6f}, {c:.6f}" for i, (a, b, c) in enumerate(xs)]
    out += ["*NODE, NSET=NPLOW"] + L1
    out += ["*NODE, NSET=NPUP"] + L2
    if mlo:
        out += ["*NODE, NSET=NWALL"] + LW
    out += ["*NODE, NSET=NREF", f"{r[0]}, 0, 0, -5", f"{r[1]}, 0, 0, -5",
            f"{r[2]}, 0, 0, {upper0 + 5:.6f}", f"{r[3]}, 0, 0, {upper0 + 5:.6f}"]
    if mlo:
        out += [f"{r[4]}, {xw - 5:.6f}, 0, 0", f"{r[5]}, {xw - 5:.6f}, 0, 0"]
    for gi, name in GROUP_NAMES.items():
        ids = np.nonzero(grp == gi)[0]
        if len(ids) == 0:
            continue
        out.append(f"*ELEMENT, TYPE=C3D10, ELSET=E{name.upper()}")
        for e in ids:
            out.append(f"{e + 1}, " + ", ".join(str(int(v) + 1) for v in tets[e]))
    out.append("*ELSET, ELSET=EBREAST")
    present = [n for gi, n in GROUP_NAMES.items() if (grp == gi).any()]
    out += [f"E{n.upper()}" for n in present]
    out.append("*ELEMENT, TYPE=C3D8, ELSET=EPLOW")
    out += [f"{e}, " + ", ".join(map(str, n)) for e, n in E1]
    out.append("*ELEMENT, TYPE=C3D8, ELSET=EPUP")
    out += [f"{e}, " + ", ".join(map(str, n)) for e, n in E2]
    if mlo:
        out.append("*ELEMENT, TYPE=C3D8, ELSET=EWALL")
        out += [f"{e}, " + ", ".join(map(str, n)) for e, n in EW]
    fixed = np.nonzero(mesh["fixed"])[0] + 1
    out.append("*NSET, NSET=NFIX")
    out += [", ".join(map(str, fixed[i:i + 12])) for i in range(0, len(fixed), 12)]
    out.append("*NSET, NSET=NRUP")
    out.append(str(r[2]))
    # slave: outer faces not on the chest wall
    bf = boundary_faces(tets)
    fx = mesh["fixed"]
    out.append("*SURFACE, NAME=SBREAST, TYPE=ELEMENT")
    nface = 0
    for e, fid, key in bf:
        if fx[list(key)].all():
            continue
        out.append(f"{e + 1}, S{fid}")
        nface += 1
    out.append("*SURFACE, NAME=SLOW, TYPE=ELEMENT")
    out += [f"{e}, {f1}" for e, _ in E1]
    out.append("*SURFACE, NAME=SUP, TYPE=ELEMENT")
    out += [f"{e}, {f2}" for e, _ in E2]
    if mlo:
        out.append("*SURFACE, NAME=SWALL, TYPE=ELEMENT")
        out += [f"{e}, S2" for e, _ in EW]
    nu = p["nu"]
    for n in present:
        c1 = p["c1_kpa"][n]
        mu = 2 * c1
        K = 2 * mu * (1 + nu) / (3 * (1 - 2 * nu))
        out += [f"*MATERIAL, NAME=M{n.upper()}", "*HYPERELASTIC, NEO HOOKE", f"{c1:.6g}, {2.0 / K:.6g}",
                "*DENSITY", f"{RHO_KG_MM3:.3e}", f"*SOLID SECTION, ELSET=E{n.upper()}, MATERIAL=M{n.upper()}"]
    out += ["*MATERIAL, NAME=MPLATE", "*ELASTIC", "1000., 0.3",
            "*SOLID SECTION, ELSET=EPLOW, MATERIAL=MPLATE", "*SOLID SECTION, ELSET=EPUP, MATERIAL=MPLATE",
            f"*RIGID BODY, NSET=NPLOW, REF NODE={r[0]}, ROT NODE={r[1]}",
            f"*RIGID BODY, NSET=NPUP, REF NODE={r[2]}, ROT NODE={r[3]}",
            "*SURFACE INTERACTION, NAME=SI", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", f"{PENALTY:g}",
            "*FRICTION", f"{p['friction']:.4f}, {STICK_SLOPE:g}",
            "*CONTACT PAIR, INTERACTION=SI, TYPE=SURFACE TO SURFACE",
            "SBREAST, SLOW", "SBREAST, SUP"]
    if mlo:
        out += ["*SOLID SECTION, ELSET=EWALL, MATERIAL=MPLATE",
                f"*RIGID BODY, NSET=NWALL, REF NODE={r[4]}, ROT NODE={r[5]}",
                "*SURFACE INTERACTION, NAME=SIW", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR",
                f"{PENALTY:g}", "*CONTACT PAIR, INTERACTION=SIW, TYPE=SURFACE TO SURFACE",
                "SBREAST, SWALL"]
    out += ["*BOUNDARY", "NFIX, 1, 2"]
    out += [f"{ri}, 1, 3" for ri in r]
    # one step (a second step restarts CalculiX's friction and diverged at once), on the
    # view's schedule of T_G0, T_G1 and HOLD
    if mlo:  # gravity first: the amplitudes' points from T_G0 = 0 on
        out += ["*AMPLITUDE, NAME=AGRAV", f"0., 0., {t_g1}, 1., 1., 1.",
                "*AMPLITUDE, NAME=APLATE", f"0., 0., {t_g1}, {hold}, 1., 1."]
    else:
        out += ["*AMPLITUDE, NAME=AGRAV", f"0., 0., {t_g0}, 0., {t_g1}, 1., 1., 1.",
                "*AMPLITUDE, NAME=APLATE", f"0., 0., {t_g0}, {hold}, {t_g1}, {hold}, 1., 1."]
    out += ["*STEP, NLGEOM, INC=5000", "*STATIC", f"0.02, 1.0, 1e-7, {max_increment:g}",
            "*DLOAD, AMPLITUDE=AGRAV", f"EBREAST, GRAV, {G_MM_S2 * g_scale:.1f}, {g[0]:.6f}, {g[1]:.6f}, {g[2]:.6f}",
            "*BOUNDARY, AMPLITUDE=APLATE", f"{r[2]}, 3, 3, {-(upper0 - gap):.6f}"]
    if mlo:  # the chest-wall section squeezed with the plates (its share of the travel)
        travel = upper0 - gap
        out += [f"{n}, 3, 3, {-travel * max(float(xs[n - 1, 2]), 0.0) / upper0:.6f}" for n in fixed]
    out += ["*NODE PRINT, NSET=NALL", "U", "*NODE PRINT, NSET=NRUP", "RF", "*END STEP"]
    path.write_text("\n".join(out) + "\n")
    return {"T0_mm": T0, "gap_mm": gap, "upper0_mm": upper0, "h0_mm": h0 + OVERLAP_MM, "angle_deg": angle,
            "solver_basis": Bs.tolist(), "y_sign": s, "gravity_solver": g.tolist(),
            "n_slave_faces": nface, "n_nodes_total": nid + len(r) - 1}


def _limit_memory() -> None:
    """Cap CalculiX's address space: after a NaN line search it allocates until the
    kernel kills it (23 GB seen), and it would take the machine's other jobs with it."""
    import resource

    cap = CCX_MEMORY_GB << 30
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))


def plate_travel(t: float | None, view: str = "CC") -> float:
    """Fraction of the upper plate's travel at step time t (the APLATE amplitude)."""
    if t is None:
        return 0.0
    t_g0, t_g1, hold = schedule(view)
    return float(np.interp(t, [0.0, t_g0, t_g1, 1.0], [0.0, hold, hold, 1.0]))


def parse_dat(path: Path, n: int) -> tuple[np.ndarray | None, float | None, float | None]:
    """Last displacement block (n nodes), the last upper-plate force (z, mN) and the step
    time of that displacement block in a .dat (one block per converged increment)."""
    txt = path.read_text().splitlines() if path.exists() else []
    disp, force, t_disp = None, None, None
    i = 0
    while i < len(txt):
        line = txt[i]
        if line.strip().startswith("displacements") and "NALL" in line:
            t_disp = float(line.split()[-1])
            u = np.zeros((n, 3))
            j = i + 2
            while j < len(txt) and txt[j].strip():
                a = txt[j].split()
                k = int(a[0])
                if k <= n:
                    u[k - 1] = [float(v) for v in a[1:4]]
                j += 1
            disp, i = u, j
            continue
        if line.strip().startswith("forces") and "NRUP" in line:
            a = txt[i + 2].split()
            force = float(a[3])
        i += 1
    return disp, force, t_disp


def _run_ccx_once(work: Path, stem: str, timeout: int) -> tuple[int, float, str]:
    """One single-threaded, memory-capped CalculiX run of ``work/stem.inp``: (rc, s, log)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_STIFFNESS="1", CCX_NPROC_EQUATION_SOLVER="1")
    t0 = time.perf_counter()
    with open(work / f"{stem}.log", "w") as fh:
        try:
            rc = subprocess.run(["ccx", "-i", stem], cwd=work, stdout=fh, stderr=subprocess.STDOUT,
                                env=env, timeout=timeout, preexec_fn=_limit_memory).returncode
        except subprocess.TimeoutExpired:
            rc = 124
    return rc, time.perf_counter() - t0, (work / f"{stem}.log").read_text()


def kept_early(t_end: float | None, force_mN: float | None, view: str) -> bool:
    """Whether a CalculiX run that stopped at step time ``t_end`` is kept at that increment:
    gravity applied in full, at least ``T_ACCEPT`` of the plate travel, and the upper plate
    pressing with at least ``MIN_CONTACT_MN``."""
    return (t_end is not None and t_end >= schedule(view)[1]
            and plate_travel(t_end, view) >= T_ACCEPT
            and force_mN is not None and abs(force_mN) >= MIN_CONTACT_MN)


def run_ccx(work: Path, mesh: dict, view: str, side: str, p: dict, timeout: int) -> dict:
    stem = f"ccx_{view.lower()}"
    res = work / f"{stem}.npz"
    if res.exists():  # re-use a finished run of the same mesh (re-rendering only)
        d = np.load(res, allow_pickle=True)
        if d["u"].shape[0] == mesh["n_nodes"]:
            meta = json.loads(str(d["meta"]))
            # the height origin follows the model frame's origin (the nipple), as in write_ccx
            meta["h0_mm"] = float((mesh["x"] @ np.asarray(meta["solver_basis"]).T)[:, 2].min()) + OVERLAP_MM
            return meta | {"u": d["u"]}
        log.warning("%s: mesh changed (%d nodes, run had %d); running CalculiX again", res,
                    mesh["n_nodes"], d["u"].shape[0])
    incs = [MAX_INCREMENT, RETRY_MAX_INCREMENT]
    for k, max_inc in enumerate(incs):
        if k:  # keep the failed try's log and status
            for ext in ("log", "sta"):
                if (work / f"{stem}.{ext}").exists():
                    (work / f"{stem}.{ext}").replace(work / f"{stem}_try{k}.{ext}")
        meta = write_ccx(work / f"{stem}.inp", mesh, view, side, p, max_increment=max_inc)
        rc, dt, logtxt = _run_ccx_once(work, stem, timeout)
        u, f, t_end = parse_dat(work / f"{stem}.dat", mesh["n_nodes"])
        meta.update({"t_reached": t_end, "max_increment": max_inc, "tries": k + 1})
        if rc == 0 and u is not None and "Job finished" in logtxt:
            break
        # CalculiX stopped before the end of the step: the truth is its last converged
        # increment, at the plate gap reached then (that gap is what the DICOM says), when
        # the upper plate has travelled at least T_ACCEPT of the way
        travel = plate_travel(t_end, view)
        if kept_early(t_end, f, view):
            break
        tail = "\n".join(logtxt.splitlines()[-6:])
        msg = f"ccx {view} failed (rc {rc}, {dt:.0f} s, t = {t_end}, largest increment {max_inc:g})"
        if k + 1 == len(incs):
            raise RuntimeError(f"{msg}:\n{tail}")
        log.warning("%s; running it again with the largest increment %g", msg, incs[k + 1])
    if rc != 0 or u is None or "Job finished" not in logtxt:
        meta["gap_target_mm"] = meta["gap_mm"]
        meta["gap_mm"] = meta["upper0_mm"] - travel * (meta["upper0_mm"] - meta["gap_mm"])
        log.warning("ccx %s stopped at t = %.3f (rc %d); the truth is that increment, gap %.1f mm "
                    "(target %.1f mm)", view, t_end, rc, meta["gap_mm"], meta["gap_target_mm"])
    meta["D_reached"] = 1.0 - meta["gap_mm"] / meta["T0_mm"]
    # back to the model frame
    Bs = np.asarray(meta["solver_basis"])
    u_model = u @ Bs
    meta.update({"ccx_s": dt, "force_upper_mN": f, "n_increments": logtxt.count("increment size=")})
    np.savez(res, u=u_model, meta=json.dumps(meta))
    return meta | {"u": u_model}


# ------------------------------------------------------------------------- embedding

def shape10(L: np.ndarray) -> np.ndarray:
    """(P, 10) quadratic tet shape functions at barycentric L (P, 4), C3D10 order."""
    N = np.empty((len(L), 10))
    N[:, :4] = L * (2 * L - 1)
    for k, (a, b) in enumerate(C3D10_EDGES):
        N[:, 4 + k] = 4 * L[:, a] * L[:, b]
    return N


def locate(x: np.ndarray, tets: np.ndarray, pts: np.ndarray, k: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Containing tet (nearest if outside) and barycentric coordinates of points."""
    c = x[tets[:, :4]]
    tree = cKDTree(c.mean(1))
    _, cand = tree.query(pts, k=min(k, len(tets)))
    cand = np.asarray(cand).reshape(len(pts), -1)
    best_e = np.zeros(len(pts), int)
    best_L = np.zeros((len(pts), 4))
    best_m = np.full(len(pts), -np.inf)
    for j in range(cand.shape[1]):
        e = cand[:, j]
        v = c[e]
        T = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], v[:, 3] - v[:, 0]], axis=2)
        lam = np.linalg.solve(T, (pts - v[:, 0])[..., None])[..., 0]
        L = np.column_stack([1 - lam.sum(1), lam])
        m = L.min(1)
        better = m > best_m
        best_e[better], best_L[better], best_m[better] = e[better], L[better], m[better]
    best_L = np.clip(best_L, 0, None)
    best_L /= best_L.sum(1, keepdims=True)
    return best_e, best_L


def deform_points(mesh: dict, u: np.ndarray, pts_model: np.ndarray) -> np.ndarray:
    e, L = locate(mesh["x"], mesh["tets"], pts_model)
    N = shape10(L)
    return pts_model + np.einsum("pk,pkd->pd", N, u[mesh["tets"][e]])


# ------------------------------------------------------------------------- rendering

def rot(theta_deg: float) -> np.ndarray:
    t = np.deg2rad(theta_deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def render_view(mesh: dict, sim: dict, view: str, side: str, p: dict, tumours_model: list,
                rotation_deg: float) -> dict:
    """Cone-beam image (canonical frame, stored orientation) and the exact annotations."""
    from regtrack.phantom.dicom_mg import canonical_to_stored_rc, stored_from_canonical
    from regtrack.virtual.raster import grid_around
    from regtrack.virtual.xray import PointSource, path_lengths, perspective

    Bs, s = np.asarray(sim["solver_basis"]), sim["y_sign"]
    xd = mesh["x"] + sim["u"]
    loc = xd @ Bs.T
    loc[:, 2] -= sim["h0_mm"]
    loc[:, 1] *= s            # regtrack's plate frame (X, Y down, h above the lower plate)
    det_gap = p["detector_gap_mm"][view]
    fixed = mesh["fixed"]
    foot = (float(loc[fixed, 0].min()), float(0.5 * (loc[fixed, 1].min() + loc[fixed, 1].max())))
    src = PointSource(foot, p["sid_mm"], -det_gap)
    # each curved tet10 rendered as its 8 linear sub-tets (its corner tet alone can invert
    # where the quadratic element does not, which showed as dark wedges)
    sub = mesh["tets"][:, SUBTETS].reshape(-1, 4)
    sub_group = np.repeat(mesh["group"], len(SUBTETS))
    P = perspective(loc, src)[:, :2]
    gr = grid_around(P, spacing=RENDER_MM, margin=6)
    lengths = path_lengths(loc, sub, sub_group, gr, source=src)
    a_c = sum(MU[g] * L for g, L in lengths.items())
    nip_loc = deform_points(mesh, sim["u"], np.zeros((1, 3))) @ Bs.T  # the nipple, deformed
    nip_loc[:, 2] -= sim["h0_mm"]
    nip_loc[:, 1] *= s
    n_img = perspective(nip_loc, src)[0, :2]
    R = rot(rotation_deg)
    Q = (P - n_img) @ R.T + n_img
    m = 12.0
    # the chest-wall image edge: at the most anterior chest-wall-plane node after the rotation (tissue
    # behind it is not imaged, as on a real mammogram)
    x0 = float(Q[mesh["on_cut"], 0].max())
    y0, y1 = float(Q[:, 1].min()) - m, float(Q[:, 1].max()) + m
    x1 = float(Q[:, 0].max()) + m
    px = p["pixel_mm"]
    shape = (int(np.ceil((y1 - y0) / px)) + 1, int(np.ceil((x1 - x0) / px)) + 1)
    off = np.array([x0, y0])
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    qx, qy = cc * px + off[0], rr * px + off[1]
    # inverse rotation to the unrotated detector plane, then sample the line integral
    dx, dy = qx - n_img[0], qy - n_img[1]
    pxu = R[0, 0] * dx + R[1, 0] * dy + n_img[0]
    pyu = R[0, 1] * dx + R[1, 1] * dy + n_img[1]
    del dx, dy, qx, qy, rr, cc
    a = ndimage.map_coordinates(a_c, [(pyu - gr.origin[1]) / RENDER_MM, (pxu - gr.origin[0]) / RENDER_MM],
                                order=1, mode="constant", cval=0.0)
    del pxu, pyu
    mask = a > 1e-4
    rng = np.random.default_rng([p["noise_seed"], 0 if view == "CC" else 1, int(abs(rotation_deg) * 1000)])
    I0 = p["quanta_per_pixel"]
    n = rng.poisson(I0 * np.exp(-a))
    pres = np.log(I0 / np.maximum(n, 0.5))
    a_ref = 1.1 * float(np.percentile(a[mask], 99.9))
    top = 4095
    canon = np.clip(np.round(pres / a_ref * top), 0, top).astype(np.uint16)
    stored = stored_from_canonical(canon, side)

    def to_canon_px(p_local3):
        pp = perspective(np.atleast_2d(p_local3), src)[:, :2]
        qq = (pp - n_img) @ R.T + n_img - off
        return qq[:, ::-1] / px  # (row, col)

    nip_rc = to_canon_px(nip_loc)[0]
    truth_t = []
    for t in tumours_model:
        pd = deform_points(mesh, sim["u"], t["points_model"])
        pl = pd @ Bs.T
        pl[:, 2] -= sim["h0_mm"]
        pl[:, 1] *= s
        rc = to_canon_px(pl)
        outline, cen = outline_from_points(rc, shape, radius_px=0.6 / px)
        if outline is None:
            continue
        cen_def = t["centroid_model"] + 0.0
        pc = deform_points(mesh, sim["u"], cen_def[None])
        pcl = pc @ Bs.T
        pcl[:, 2] -= sim["h0_mm"]
        pcl[:, 1] *= s
        truth_t.append({
            "label": t["label"], "volume_mm3": t["volume_mm3"], "centroid_lps_mm": t["centroid_lps_mm"],
            "outline_dicom_rc": canonical_to_stored_rc(outline, shape=shape, laterality=side).tolist(),
            "centroid_dicom_rc": canonical_to_stored_rc(cen, shape=shape, laterality=side).tolist(),
            "centroid_canonical_mm": (cen[::-1] * px).tolist(),
            "volume_centroid_projected_dicom_rc": canonical_to_stored_rc(
                to_canon_px(pcl)[0], shape=shape, laterality=side).tolist(),
            "area_mm2": float(polygon_area(outline) * px * px)})
    return {"stored": stored, "shape": shape, "truth": {
        "view": view, "laterality": side, "rotation_deg": rotation_deg, "image_shape": list(shape),
        "pixel_mm": px, "nipple_dicom_rc": canonical_to_stored_rc(nip_rc, shape=shape, laterality=side).tolist(),
        "nipple_canonical_mm": (nip_rc[::-1] * px).tolist(),
        "source_foot_plate_mm": list(foot), "detector_gap_mm": det_gap, "sid_mm": p["sid_mm"],
        "offset_mm": off.tolist(), "nipple_detector_unrotated_mm": n_img.tolist(),
        "image_map": "canonical_mm = R(rot) (p_detector - n') + n' - offset; p_detector = cone-beam "
                     "projection of the plate-frame point; R = [[c,-s],[s,c]]; DICOM rc = IHE storage of "
                     "canonical (right breast flipped left-right)",
        "tumours": truth_t, "A_ref": a_ref}}


def polygon_area(rc: np.ndarray) -> float:
    x, y = rc[:, 1], rc[:, 0]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def outline_from_points(rc: np.ndarray, shape, radius_px: float):
    """Outline (row, col) and area centroid of the region covered by projected points."""
    from shapely.geometry import Polygon
    from skimage import measure, morphology

    lo = np.floor(rc.min(0)).astype(int) - 20
    hi = np.ceil(rc.max(0)).astype(int) + 20
    sub = np.zeros(tuple(hi - lo + 1), bool)
    ij = np.round(rc - lo).astype(int)
    sub[ij[:, 0], ij[:, 1]] = True
    rad = max(1, int(round(radius_px)))
    sub = ndimage.binary_dilation(sub, morphology.disk(rad))
    sub = ndimage.binary_closing(sub, morphology.disk(3 * rad))
    sub = ndimage.binary_fill_holes(sub)
    lab, n = ndimage.label(sub)
    if n == 0:
        return None, None
    big = 1 + int(np.argmax(ndimage.sum_labels(sub, lab, np.arange(1, n + 1))))
    sub = lab == big
    cs = measure.find_contours(np.pad(sub, 1).astype(float), 0.5)
    c = max(cs, key=len) - 1 + lo
    poly = Polygon(c[:, ::-1]).simplify(0.3)
    if not poly.is_valid:
        poly = poly.buffer(0)
    # the visible part: clipped by the image (the chest-wall edge can cut a deep tumour)
    from shapely.geometry import box

    vis = poly.intersection(box(0.0, 0.0, shape[1] - 1.0, shape[0] - 1.0))
    if vis.is_empty:
        return None, None
    if vis.geom_type != "Polygon":
        vis = max(getattr(vis, "geoms", [vis]), key=lambda g: g.area)
    if vis.area < poly.area - 1e-6:
        log.warning("tumour outline clipped by the image edge: %.0f %% visible", 100 * vis.area / poly.area)
    poly = vis
    xy = np.asarray(poly.exterior.coords)[:-1]
    cen = np.array([poly.centroid.y, poly.centroid.x])
    return xy[:, ::-1], cen


def write_dicom(path: Path, stored: np.ndarray, view: str, side: str, case_id: str, p: dict, sim: dict,
                truth: dict) -> None:
    import pydicom
    from regtrack.phantom.dicom_mg import write_mg_dicom

    write_mg_dicom(path, stored, view=view, laterality=side, spacing_mm=p["pixel_mm"],
                   uid_seed=f"truth-{case_id}", patient=case_id, bits_stored=12, compression_ratio=10.0,
                   instance_number=1 if view == "CC" else 2, description=f"{side}{view} (CalculiX truth)")
    ds = pydicom.dcmread(path)
    sid, gap = p["sid_mm"], p["detector_gap_mm"][view]
    ssd = sid - gap
    ds.BodyPartThickness = f"{sim['gap_mm']:.1f}"
    if sim.get("force_upper_mN") is not None:
        ds.CompressionForce = f"{abs(sim['force_upper_mN']) / 1000.0:.1f}"
    ds.PositionerPrimaryAngle = f"{(sim['angle_deg'] if side == 'R' else -sim['angle_deg']):.1f}" \
        if view == "MLO" else "0"
    ds.DistanceSourceToDetector = f"{sid:.1f}"
    ds.DistanceSourceToPatient = f"{ssd:.1f}"
    ds.EstimatedRadiographicMagnificationFactor = f"{sid / (ssd - 0.5 * sim['gap_mm']):.4f}"
    ds.ImagerPixelSpacing = [p["pixel_mm"], p["pixel_mm"]]
    ds.save_as(path, enforce_file_format=True)


# ------------------------------------------------------------------------- case folders

def write_case(root: Path, name: str, exam: str, side: str, views: dict, with_outline: bool,
               rot0: bool) -> Path:
    case = root / name
    if case.exists():
        shutil.rmtree(case)
    (case / "mri").mkdir(parents=True)
    (case / "mammo").mkdir()
    src = find_zip(exam, "simple")
    shutil.copy2(src, case / "mri" / src.name)
    lines = ["# Ground-truth case made by pipelines/make_truth_cases.py (CalculiX truth);",
             "# its truth lives outside this folder and is never read by regtrack.",
             "[case]", f'id = "{name}"',
             f'title = "Pelicano exam {exam} {side} breast, CalculiX truth'
             f'{", unrotated" if rot0 else ""}{", tumour outline" if with_outline else ", tracking mode"}"',
             "", "[mri]", f'labels = "mri/{src.name}"', 'scheme = "pelicano-simple"', f'side = "{side}"']
    for v, info in views.items():
        stem = v.lower()
        shutil.copy2(info["dicom"], case / "mammo" / f"{stem}.dcm")
        lines += ["", f"[views.{v}]", f'mammogram = "mammo/{stem}.dcm"']
        if with_outline and info["tumours"]:
            polys = [t["outline_dicom_rc"] for t in info["tumours"]]
            doc = {"points_rc": polys[0]} if len(polys) == 1 else {"polygons_rc": polys}
            (case / "mammo" / f"{stem}_tumour.json").write_text(json.dumps(doc))
            lines.append(f'tumour_polygon = "mammo/{stem}_tumour.json"')
    (case / "case.toml").write_text("\n".join(lines) + "\n")
    return case


def simulate_view(work: Path, mesh_of, view: str, side: str, p: dict, timeout: int) -> tuple[dict, int]:
    """:func:`run_ccx` of ``view`` on ``mesh_of(0)[0]``; a view CalculiX cannot finish there
    (at either increment) is run on the mesh of the next refinement level ``mesh_of(k)[0]``
    (``REFINE ** k`` times the elements), in the folder ``work / refined<k>``, up to
    ``REFINE_LEVELS``.  Returns the simulation and its level; raises RuntimeError with every
    level's failure."""
    errors = []
    for level in range(REFINE_LEVELS + 1):
        folder = work / f"refined{level}" if level else work
        folder.mkdir(parents=True, exist_ok=True)
        try:
            return run_ccx(folder, mesh_of(level)[0], view, side, p, timeout), level
        except RuntimeError as e:
            errors.append(f"{mesh_of(level)[0]['n_tets']} elements: {str(e).splitlines()[0]}")
            if level < REFINE_LEVELS:
                log.warning("%s: %s; meshing %g times finer", view, errors[-1], REFINE)
    raise RuntimeError("; ".join(errors))


def model_tumours(geo: dict, mesh: dict) -> list[dict]:
    """The MRI tumours of ``geo`` in the model frame of ``mesh`` (its basis and nipple
    origin): surface points (at most 20,000, drawn) and centroid (mm)."""
    B, o = mesh["basis"], mesh["origin_lps"]
    out = []
    for t in geo["tumours"]:
        pts = (t["surface_points_lps"] - o) @ B.T
        if len(pts) > 20000:
            pts = pts[np.random.default_rng(0).choice(len(pts), 20000, replace=False)]
        out.append({**{k: v for k, v in t.items() if k != "surface_points_lps"}, "points_model": pts,
                    "centroid_model": (np.asarray(t["centroid_lps_mm"]) - o) @ B.T})
    return out


def make_case(exam: str, side: str, views: list[str], out: Path, seed: int, target_tets: int,
              timeout: int) -> dict:
    name = f"pel{exam}{side}"
    work = out / "work" / name
    work.mkdir(parents=True, exist_ok=True)
    p = draw_params(exam, side, seed)
    t0 = time.perf_counter()
    geo = breast_geometry(exam, side)
    meshes: dict = {}

    def mesh_of(level: int) -> tuple[dict, list, dict]:
        """The mesh of refinement ``level`` (``REFINE ** level`` times ``target_tets``),
        its tumours in the model frame and its record, made once."""
        if level not in meshes:
            t1 = time.perf_counter()
            o = meshes[0][0]["origin_lps"] if level else None
            m = build_mesh(geo, side, round(target_tets * REFINE**level), origin_lps=o)
            log.info("%s: mesh %d nodes, %d tet10, size %.1f mm, groups %s, fixed %d", name, m["n_nodes"],
                     m["n_tets"], m["element_size_mm"], m["group_volume_mm3"], int(m["fixed"].sum()))
            rec = {k: m[k] for k in ("n_nodes", "n_tets", "element_size_mm", "surface", "volume_mm3",
                                     "group_volume_mm3", "min_vol")} | {
                "n_fixed": int(m["fixed"].sum()), "chest_cut_ant_mm": geo["cut_ant_mm"],
                "nipple_lps_mm": m["origin_lps"].tolist(), "mesh_s": time.perf_counter() - t1,
                "element": "C3D10 (gmsh order 2, straight-sided)"}
            meshes[level] = (m, model_tumours(geo, m), rec)
        return meshes[level]

    mesh, tumours_model, rec = mesh_of(0)
    doc = {"note": "Hidden ground truth; regtrack never reads this file.", "exam": exam, "side": side,
           "case": name, "params": p, "mesh": rec,
           "tumours_mri": [{k: v for k, v in t.items() if k not in ("points_model", "centroid_model")}
                           for t in tumours_model],
           "views": {}, "views_rot0": {}}
    per_variant = {"rot": {}, "rot0": {}}
    for v in views:
        try:
            sim, level = simulate_view(work, mesh_of, v, side, p, timeout)
        except RuntimeError as e:  # the other view may still make a case
            log.error("%s %s: %s", name, v, str(e).splitlines()[0])
            doc.setdefault("failed_views", {})[v] = str(e).splitlines()[0]
            continue
        mesh, tumours_model, rec = mesh_of(level)
        log.info("%s %s: ccx %.0f s, gap %.1f mm (T0 %.1f), force %.1f N", name, v, sim.get("ccx_s", -1),
                 sim["gap_mm"], sim["T0_mm"], abs(sim.get("force_upper_mN") or 0) / 1000)
        simmeta = {k: val for k, val in sim.items() if k != "u"}
        simmeta["max_displacement_mm"] = float(np.linalg.norm(sim["u"], axis=1).max())
        if level:  # the view's own mesh
            simmeta["mesh"] = rec
        for var, rotdeg in (("rot", p["rotation_deg"][v]), ("rot0", 0.0)):
            r = render_view(mesh, sim, v, side, p, tumours_model, rotdeg)
            dpath = work / f"{v.lower()}_{var}.dcm"
            write_dicom(dpath, r["stored"], v, side, f"{name}", p, sim, r["truth"])
            per_variant[var][v] = {"dicom": dpath, "tumours": r["truth"]["tumours"]}
            doc["views" if var == "rot" else "views_rot0"][v] = r["truth"] | {"simulation": simmeta}
    if not per_variant["rot"]:
        raise RuntimeError(f"no view of {name} converged in CalculiX: {doc.get('failed_views')}")
    cases = out / "cases"
    cases.mkdir(parents=True, exist_ok=True)
    write_case(cases, f"{name}_track", exam, side, per_variant["rot"], with_outline=False, rot0=False)
    write_case(cases, f"{name}_paper", exam, side, per_variant["rot"], with_outline=True, rot0=False)
    write_case(cases, f"{name}_paper_rot0", exam, side, per_variant["rot0"], with_outline=True, rot0=True)
    doc["total_s"] = time.perf_counter() - t0
    (out / "truth").mkdir(exist_ok=True)
    (out / "truth" / f"{name}.json").write_text(json.dumps(doc, indent=1, default=_json_default))
    return doc


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--exams", required=True, help="comma-separated exam+side, e.g. 03R,10R,11L")
    ap.add_argument("--views", default="CC,MLO")
    ap.add_argument("--out", default="reports/truth")
    ap.add_argument("--seed", type=int, default=52)
    ap.add_argument("--target-tets", type=int, default=1200)
    ap.add_argument("--ccx-timeout", type=int, default=1800)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    out = Path(a.out)
    views = [v.strip().upper() for v in a.views.split(",")]
    rc = 0
    for item in a.exams.split(","):
        m = re.fullmatch(r"(\d\d)([LR])", item.strip())
        if not m:
            raise SystemExit(f"--exams: {item!r} is not like 03R")
        try:
            make_case(m.group(1), m.group(2), views, out, a.seed, a.target_tets, a.ccx_timeout)
        except Exception as e:  # report and go on with the next exam
            log.error("exam %s failed: %s", item, e)
            rc = 1
    return rc


if __name__ == "__main__":
    sys.exit(main())
