"""``build_model``: label map -> quality tetrahedral :class:`BreastModel` (issue 3).

Pipeline: :func:`~regtrack.model.prepare.prepare_breast` (side, chest wall, crop, tumours)
-> :func:`~regtrack.model.boundary.make_surfaces` (smoothed marching-cubes surfaces,
isotropically remeshed with pymeshlab and checked for intersections; retried) ->
gmsh (:mod:`regtrack.model.mesher`, in a child process with a timeout) -> checks
(:mod:`regtrack.model.checks`), retried with other settings when a check fails
(:func:`attempt_plan`; a tumour whose meshed volume misses its voxel volume is first refined
locally, :func:`refine_tumour_factors`) -> anatomical frame, nipple node, chest-wall nodes,
skin triangles.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from regtrack.config import to_table
from regtrack.errors import MeshQualityError
from regtrack.imaging.volume import LabelVolume
from regtrack.model import checks
from regtrack.model.config import MeshConfig
from regtrack.model.boundary import make_surfaces
from regtrack.model.geometry import detect_nipple, make_frame, skin_vertices, target_size, tumour_sizes
from regtrack.model.labels import LabelScheme
from regtrack.model.mesher import MeshRequest, MeshResult, run_gmsh
from regtrack.model.prepare import PreparedBreast, prepare_breast
from regtrack.model.types import TISSUE, TUMOUR, BreastModel

log = logging.getLogger(__name__)

# nodes closer than this (voxels) to a cut plane lie on the cut (marching cubes puts the cut
# face within a fraction of a voxel of the plane)
CUT_TOL_VOX = 0.5


def attempt_plan(config: MeshConfig) -> list[dict]:
    """Settings of the successive meshing attempts (first = the configured ones).

    Each later attempt changes the formulation, never for one exam: the other 3-D
    algorithm (a gmsh failure); then the rim between skin and cut faces rounded over
    ``retry_rim_fraction`` of the element size (``rim_fraction``; a thin wedge of tissue
    between the skin and a cut plane folds when remeshed: Pelicano exam 41 left failed
    every other setting); then more surface smoothing and a larger feature angle; then
    the Delaunay algorithm on smaller elements; further attempts shrink the elements.
    """
    other = "hxt" if config.algorithm != "hxt" else "delaunay"
    s0, f0, rim = config.smoothing_mm, config.feature_angle_deg, config.retry_rim_fraction
    s1 = s0 * 1.5 + 0.5
    plan = [
        {"algorithm": config.algorithm, "smoothing_mm": s0, "size_factor": 1.0, "feature_angle_deg": f0, "rim_fraction": 0.0},
        {"algorithm": other, "smoothing_mm": s0, "size_factor": 1.0, "feature_angle_deg": f0, "rim_fraction": 0.0},
        {"algorithm": config.algorithm, "smoothing_mm": s0, "size_factor": 1.0, "feature_angle_deg": f0, "rim_fraction": rim},
        {"algorithm": config.algorithm, "smoothing_mm": s1, "size_factor": 1.0, "feature_angle_deg": f0 + 15, "rim_fraction": rim},
        {"algorithm": "delaunay", "smoothing_mm": s1, "size_factor": 0.8, "feature_angle_deg": f0 + 15, "rim_fraction": rim},
    ]
    while len(plan) < config.max_attempts:
        p = dict(plan[-1])
        p["size_factor"] *= 0.85
        plan.append(p)
    return plan[: config.max_attempts]


def evaluate(res: MeshResult, prep: PreparedBreast, sdf_outer: checks.SignedDistance,
             sdf_tumours: list[checks.SignedDistance], config: MeshConfig) -> tuple[dict, list[str]]:
    """Quality figures of a mesh and the list of failed checks."""
    fig = checks.quality_figures(res.points, res.tets, res.gamma)
    fig["gmsh_min_sj_min"] = float(res.min_sj.min())
    vv = prep.volume.voxel_volume
    vol = checks.tet_volumes(res.points, res.tets)
    ref = float(prep.breast.sum() * vv)
    fig["volume_mm3"] = float(vol.sum())
    fig["voxel_volume_mm3"] = ref
    fig["volume_error"] = float(vol.sum() / ref - 1.0)
    tum = []
    for k, t in enumerate(prep.tumours.kept, start=1):
        v = float(vol[res.tumour_id == k].sum())
        kept = prep.info.get("tumours_kept", [])
        uncut = kept[k - 1].get("uncut_volume_mm3", t.volume_mm3) if k <= len(kept) else t.volume_mm3
        # reference: the voxel volume inside the model (after the cuts); the uncut one is kept
        tum.append({"id": k, "volume_mm3": v, "voxel_volume_mm3": t.volume_mm3,
                    "volume_error": v / t.volume_mm3 - 1.0, "uncut_voxel_volume_mm3": uncut})
    fig["tumours"] = tum
    bf, _ = checks.boundary_faces(res.tets)
    bn = np.unique(bf)
    on_plane = np.zeros(len(res.points), bool)
    for p in prep.planes:
        on_plane |= np.abs(p.distance(res.points)) < CUT_TOL_VOX * float(np.mean(prep.volume.spacing))
    skin_nodes = bn[~on_plane[bn]]
    d = np.abs(sdf_outer(res.points[skin_nodes])) if len(skin_nodes) else np.zeros(1)
    sp = float(np.mean(prep.volume.spacing))
    fig["surface_distance_mean_mm"] = float(d.mean())
    fig["surface_distance_max_mm"] = float(d.max())
    tdist = []
    if len(prep.tumours.kept):
        itf = checks.interface_faces(res.tets, res.tumour_id)
        for k, sdf in enumerate(sdf_tumours, start=1):
            nodes = np.intersect1d(np.unique(itf), np.unique(res.tets[res.tumour_id == k]))
            if len(nodes):
                tdist.append(float(np.abs(sdf(res.points[nodes])).mean()))
    fig["tumour_surface_distance_mean_mm"] = tdist
    fail = []
    if fig["n_inverted"]:
        fail.append(f"{fig['n_inverted']} inverted/zero-volume tets")
    if fig["min_dihedral_deg"] < config.min_dihedral_deg:
        fail.append(f"min dihedral {fig['min_dihedral_deg']:.2f} deg < {config.min_dihedral_deg}")
    if fig["gamma_p5"] < config.min_gamma_p5:
        fail.append(f"gamma 5th percentile {fig['gamma_p5']:.3f} < {config.min_gamma_p5}")
    if abs(fig["volume_error"]) > config.max_volume_error:
        fail.append(f"volume error {100 * fig['volume_error']:.2f}% > {100 * config.max_volume_error:g}%")
    for k in tumour_misses(tum, config):
        fail.append(f"tumour {tum[k]['id']} volume error {100 * tum[k]['volume_error']:.1f}% > {100 * config.max_tumour_volume_error:g}%")
    if fig["surface_distance_mean_mm"] > config.max_mean_surface_distance_vox * sp:
        fail.append(f"mean surface distance {fig['surface_distance_mean_mm']:.2f} mm > {config.max_mean_surface_distance_vox} voxel")
    return fig, fail


def tumour_misses(tumours: list[dict], config: MeshConfig) -> list[int]:
    """0-based indices of the checked tumours (voxel volume >= ``check_tumour_min_ml``)
    whose meshed volume misses their voxel volume by more than ``max_tumour_volume_error``."""
    return [k for k, t in enumerate(tumours)
            if t["voxel_volume_mm3"] >= 1000.0 * config.check_tumour_min_ml
            and abs(t["volume_error"]) > config.max_tumour_volume_error]


def refine_tumour_factors(tumours: list[dict], factors: list[float], config: MeshConfig) -> list[float] | None:
    """Per-tumour refinement factors after a mesh whose tumour volumes were measured.

    A tumour's surface is a smoothed level set of its voxels, remeshed to its element size
    ``h_t`` and meshed with that size (:func:`~regtrack.model.geometry.tumour_sizes`).  On a
    tumour a few voxels across, the smoothing (sigma about one voxel), the marching-cubes
    step and the chords of edges ``h_t`` take a share of its volume that falls as
    ``h_t`` and sigma fall; so each missing tumour (:func:`tumour_misses`) gets both
    multiplied by ``tumour_refine_factor`` (a local size field: the rest of the mesh keeps
    its size).  No factor goes below ``tumour_refine_factor ** tumour_refinements``.

    Returns
    -------
    list of float or None
        The new factors, or None when no missing tumour can be refined further.
    """
    floor = config.tumour_refine_factor ** config.tumour_refinements * (1.0 + 1e-9)
    out = list(factors)
    changed = False
    for k in tumour_misses(tumours, config):
        if k < len(out) and out[k] > floor:
            out[k] *= config.tumour_refine_factor
            changed = True
    return out if changed else None


def _orient(res: MeshResult) -> MeshResult:
    v = checks.tet_volumes(res.points, res.tets)
    neg = v < 0
    if neg.mean() > 0.5:  # another vertex-ordering convention: flip all
        res.tets = res.tets[:, [0, 1, 3, 2]]
    return res


def _progress(progress, msg: str) -> None:
    if progress is not None:
        progress(msg)
    log.info("%s", msg)


def build_model(labels: LabelVolume, *, scheme: LabelScheme, config: MeshConfig,
                side: str | None = None, nipple_lps: np.ndarray | None = None,
                progress=None) -> BreastModel:
    """Patient model of one breast from a segmented MRI label map.

    Parameters
    ----------
    labels : LabelVolume
        Label map with its voxel -> LPS (mm) affine; bilateral or one breast.
    scheme : LabelScheme
        Which label values are tissue, tumour, skin, muscle, background.
    config : MeshConfig
        Meshing settings (``[model]`` of case.toml).
    side : {"L", "R"}, optional
        Breast to model; default: the one holding the tumour (reason logged and recorded).
    nipple_lps : (3,) array, optional
        Explicit nipple (LPS, mm); wins over detection (the nearest skin node is used).
    progress : callable, optional
        Called with a short message at each stage.

    Returns
    -------
    BreastModel
        Points in the model frame (origin nipple, x anterior, y superior, z right), mm.

    Raises
    ------
    InputFileError
        No breast label, impossible side.
    MeshQualityError
        Every meshing attempt failed its checks (``figures`` holds the last measures).
    """
    t0 = time.perf_counter()
    _progress(progress, "selecting the breast")
    prep = prepare_breast(labels, scheme=scheme, config=config, side=side)
    stages = {"prepare": time.perf_counter() - t0, "surfaces": 0.0, "gmsh": 0.0, "checks": 0.0}
    sdf_outer = checks.SignedDistance.of_mask(prep.breast, prep.volume.affine)
    sdf_t = [checks.SignedDistance.of_mask(prep.tumours.labelled == t.component, prep.volume.affine)
             for t in prep.tumours.kept]
    nipple_target, nipple_src = _nipple_target(prep, config, nipple_lps)
    attempts, best = [], None
    size_scale = 1.0
    surf_cache: dict = {}
    plan = attempt_plan(config)
    # per-tumour factor on the element size and smoothing, lowered by refine_tumour_factors
    # for a tumour whose meshed volume misses its voxel volume; kept for later attempts
    tfac = [1.0] * len(prep.tumours.kept)
    rounds = 0  # refinement rounds of the current attempt
    i = 0
    while i < len(plan):
        a = plan[i]
        h = target_size(prep.info["breast_voxel_volume_mm3"], config) * a["size_factor"] * size_scale
        hts = [s * f for s, f in zip(tumour_sizes([t.volume_mm3 for t in prep.tumours.kept], h, config), tfac)]
        tsm = [config.tumour_smoothing_mm * f for f in tfac]
        rim_mm = a["rim_fraction"] * h
        key = (a["smoothing_mm"], round(h, 6), rim_mm, tuple(round(x, 6) for x in hts), tuple(round(x, 6) for x in tsm))
        rec = {"attempt": i + 1, **a, "size_mm": h, "tumour_sizes_mm": hts, "tumour_smoothing_mm": tsm,
               "tumour_refinement": rounds}
        if key not in surf_cache:
            _progress(progress, f"surfaces (smoothing {a['smoothing_mm']:.2f} mm, edge {h:.2f} mm, rim {rim_mm:.2f} mm)")
            ts = time.perf_counter()
            surf_cache[key] = make_surfaces(
                prep, edge_mm=h, tumour_edges_mm=hts, smoothing_mm=a["smoothing_mm"],
                tumour_smoothing_mm=tsm, clearance_mm=config.tumour_clearance_mm,
                feature_fraction=config.feature_fraction, small_angle_deg=config.min_triangle_angle_deg,
                step_vox=config.surface_step_vox, rim_mm=rim_mm,
                nipple_mm=nipple_target)
            surf_cache[key].info["seconds"] = time.perf_counter() - ts
            stages["surfaces"] += surf_cache[key].info["seconds"]
        surfs = surf_cache[key]
        rec["surfaces"] = {**surfs.info, "tries": surfs.tries, "checks": [c.to_dict() for c in surfs.checks],
                           "problems": surfs.problems}
        if surfs.problems:
            rec["error"] = "surface checks failed: " + "; ".join(surfs.problems)
            log.warning("meshing attempt %d: %s", i + 1, rec["error"])
            attempts.append(rec)
            i, rounds = i + 1, 0
            continue
        req = MeshRequest(surfs.outer.verts, surfs.outer.faces, [s.verts for s in surfs.tumours],
                          [s.faces for s in surfs.tumours], size_mm=h, tumour_sizes_mm=hts,
                          refine_distance_mm=config.refine_distance_mm, algorithm=a["algorithm"],
                          threads=config.threads, optimize_netgen=config.optimize_netgen,
                          feature_angle_deg=a["feature_angle_deg"])
        _progress(progress, f"meshing attempt {i + 1}/{len(plan)}: {a['algorithm']}, h = {h:.2f} mm")
        tg = time.perf_counter()
        try:
            res = _orient(run_gmsh(req, timeout_s=config.timeout_s))
            stages["gmsh"] += time.perf_counter() - tg
        except (TimeoutError, RuntimeError) as exc:
            rec["error"] = str(exc)
            log.warning("meshing attempt %d failed: %s", i + 1, exc)
            attempts.append(rec)
            i, rounds = i + 1, 0
            continue
        tc = time.perf_counter()
        fig, fail = evaluate(res, prep, sdf_outer, sdf_t, config)
        stages["checks"] += time.perf_counter() - tc
        rec.update({"gmsh_seconds": res.seconds, "failed_checks": fail, "figures": fig})
        attempts.append(rec)
        miss = fig["n_nodes"] / config.target_nodes - 1.0
        if (config.element_size_mm is None and abs(miss) > config.node_tolerance and size_scale == 1.0):
            size_scale = (fig["n_nodes"] / config.target_nodes) ** (1.0 / 3.0)
            log.info("%d nodes vs target %d: re-sizing by %.3f", fig["n_nodes"], config.target_nodes, size_scale)
            best = (res, fig) if not fail else best
            continue  # same attempt settings, new size
        if not fail:
            best = (res, fig)
            break
        refined = refine_tumour_factors(fig["tumours"], tfac, config)
        if refined is not None:
            tfac = refined
            if rounds < config.tumour_refinements and all(f.startswith("tumour ") for f in fail):
                rounds += 1
                log.info("meshing attempt %d: %s; refining those tumours (round %d of %d)", i + 1,
                         "; ".join(fail), rounds, config.tumour_refinements)
                continue  # same attempt settings, finer tumours
        log.warning("meshing attempt %d failed its checks: %s", i + 1, "; ".join(fail))
        if best is not None:
            # only the re-sizing for the node count keeps a passed mesh in hand: it met
            # every check, so it is used rather than trading checks for the node count
            log.warning("keeping the mesh before re-sizing: %d nodes (target %d), every check passed",
                        best[1]["n_nodes"], config.target_nodes)
            break
        i, rounds = i + 1, 0
    if best is None:
        last = attempts[-1] if attempts else {}
        raise MeshQualityError(
            f"meshing failed after {len(attempts)} attempt(s); last: "
            + ("; ".join(last.get("failed_checks", [])) or last.get("error", "?"))
            + "; try [model] element_size_mm, smoothing_mm or algorithm", figures={"attempts": attempts})
    res, fig = best
    model = _assemble(res, prep, nipple_target, nipple_src, config)
    if nipple_lps is not None:  # the user's point; target_lps_mm is its projection on the skin
        model.meta["nipple"]["given_lps_mm"] = np.asarray(nipple_lps, float).tolist()
    model.meta.update({
        "settings": to_table(config), "scheme": scheme.to_dict(), "preparation": prep.info,
        "quality": fig, "attempts": attempts, "seconds_total": time.perf_counter() - t0,
        "seconds_stages": {k: round(v, 3) for k, v in stages.items()},
        "source": str(labels.source) if labels.source is not None else None,
    })
    _progress(progress, f"model: {model.n_nodes} nodes, {model.n_tets} tets, {len(prep.tumours.kept)} tumour(s)")
    return model


def _nipple_target(prep: PreparedBreast, config: MeshConfig, nipple_lps) -> tuple[np.ndarray, str]:
    """Nipple point (LPS mm) on a dense marching-cubes skin (vertex spacing about one
    voxel): the skin vertex nearest the explicit nipple when one is given, else detected.

    Either way the point is pinned as a node of the remeshed surface (``make_surfaces``),
    so the model's nipple node is the anatomical nipple whatever the element size.  An
    explicit point is projected onto the skin first, because pinning a node off the surface
    would dent or spike it (before, an explicit nipple took the nearest node of the coarse
    mesh: 4.7 mm away on the 7.5 mm phantom truth mesh, which turned the phantom's
    mammograms by about 2-5 deg against the pipeline's).
    """
    from regtrack.model.boundary import outer_field
    from regtrack.model.surfaces import extract_surface

    g = outer_field(prep, smoothing_mm=config.smoothing_mm, feature_mm=0.0)
    dense = extract_surface(g, prep.volume.affine, step=1, relax_iterations=0)
    sv = skin_vertices(dense, prep.planes, tol_mm=0.5 * float(np.mean(prep.volume.spacing)))
    if nipple_lps is not None:
        target = np.asarray(nipple_lps, float)
        d = np.linalg.norm(dense.verts[sv] - target, axis=1)
        if d.min() > 5.0:
            log.warning("explicit nipple lies %.1f mm from the skin; using the nearest skin point", d.min())
        return dense.verts[sv][int(np.argmin(d))].astype(float), "explicit"
    return detect_nipple(dense.verts[sv], prep.chest_wall.plane.normal, depth_mm=config.nipple_depth_mm), "detected"


def _assemble(res: MeshResult, prep: PreparedBreast, target: np.ndarray, nip_src: str,
              config: MeshConfig) -> BreastModel:
    pts = res.points
    cw = prep.chest_wall.plane
    tol = CUT_TOL_VOX * float(np.mean(prep.volume.spacing))
    bf, _ = checks.boundary_faces(res.tets)
    fn = np.cross(pts[bf[:, 1]] - pts[bf[:, 0]], pts[bf[:, 2]] - pts[bf[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    kinds = {}
    face_cut = np.zeros(len(bf), bool)
    for p in prep.planes:
        on = np.abs(p.distance(pts)) < tol
        fc = on[bf].all(axis=1) & (fn @ p.normal < -0.9)  # outward normal = -plane normal
        kinds[p.kind] = kinds.get(p.kind, 0) + int(fc.sum())
        face_cut |= fc
    skin = bf[~face_cut]
    fixed = np.abs(cw.distance(pts)) < tol
    anterior = cw.normal
    skin_nodes = np.unique(skin)
    dn = np.linalg.norm(pts[skin_nodes] - target, axis=1)
    nipple = int(skin_nodes[np.argmin(dn)])
    frame = make_frame(anterior, prep.side, pts[nipple])
    xm = frame.to_model(pts)
    if config.fix_extra:
        bn = np.unique(bf)
        top = bn[xm[bn, 1] >= xm[bn, 1].max() - config.fix_extra_band_mm]
        mids = [p for p in prep.planes if p.kind == "midline"]
        if mids:
            med = bn[np.abs(mids[0].distance(pts[bn])) < config.fix_extra_band_mm]
        else:
            zl = frame.lateral_sign * xm[bn, 2]
            med = bn[zl <= zl.min() + config.fix_extra_band_mm]
        fixed[top] = True
        fixed[med] = True
    region = np.where(res.tumour_id > 0, TUMOUR, TISSUE)
    cen = pts[res.tets].mean(axis=1)
    ijk = np.rint(prep.volume.world_to_index(cen)).astype(int)
    ijk = np.clip(ijk, 0, np.array(prep.volume.shape) - 1)
    tl = np.rint(prep.volume.data[ijk[:, 0], ijk[:, 1], ijk[:, 2]]).astype(np.int64)
    meta = {"nipple": {"source": nip_src, "lps_mm": pts[nipple].tolist(), "target_lps_mm": np.asarray(target).tolist(),
                       "distance_to_target_mm": float(dn.min())},
            "boundary_faces": {"skin": int(len(skin)), **kinds}, "n_fixed": int(fixed.sum())}
    return BreastModel(points=xm, tets=res.tets, region=region, tumour_id=res.tumour_id, skin=skin,
                       fixed=fixed, nipple=nipple, frame=frame, tissue_label=tl, meta=meta)


__all__ = ["build_model", "attempt_plan", "evaluate", "tumour_misses", "refine_tumour_factors"]
