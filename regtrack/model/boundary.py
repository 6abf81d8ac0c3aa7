"""Boundary surfaces of the model: outer (skin + cut faces) and one per tumour.

For each surface: smoothed volume-preserving level set (:mod:`regtrack.model.surfaces`),
marching cubes at a step of about ``L / 2.5`` voxels, then isotropic remeshing to the
element size ``L`` (:mod:`regtrack.model.remesh`), checked for intersections, open edges
and small angles; a failed check is retried with the next :data:`~regtrack.model.remesh.REMESH_TRIES`
setting.

Details that the element size forces:

* **Features thinner than the elements** (a 2-3 voxel crevice at the chest wall of exam
  02) cannot be represented by triangles of edge ``L``: the remeshed surface folds
  through itself there.  The breast mask is therefore closed and then opened with a ball
  of radius ``r = feature_fraction * L`` (distance-transform morphology), which removes
  crevices and ridges narrower than about ``2 r``; the level set's iso-value then restores
  the voxel volume (:func:`~regtrack.model.surfaces.smooth_levelset`).  Each tumour mask
  gets the same treatment with its own element size (exam 02's 52 ml tumour folded too),
  with a doubled radius in the later tries.
* **Tumour clearance**: each tumour level set is intersected with
  ``d_out - c`` (``d_out`` the distance (mm) inside the smoothed outer region, ``c`` the
  clearance), so a tumour touching the skin or a cut plane keeps a gap of ``c`` to the
  outer surface; a tumour cut by the chest wall loses the slab within ``c`` of the plane.
  ``c`` is the configured clearance plus ``a L``: the remeshed outer surface's chords lie
  inside its level set by up to ``L^2 / (8 R)`` (``R`` the radius of curvature, a few mm
  at the rim of a cut face); ``a`` = 0.2, then 0.35 in the later tries.  The trimmed rim
  is rounded over about 1 mm (:func:`smooth_min`).
* **Rounded rim** (a retry, :func:`outer_field`): where the skin meets a cut plane at a few
  degrees, the thin wedge's remeshed triangles fold onto the cut face; the later attempts
  cut with a smooth minimum over half an element, which rounds the rim and shaves the wedge.
* **Tumour volume**: each tumour's iso-value is shifted so that its marching-cubes surface
  encloses the tumour's voxel volume (:func:`~regtrack.model.surfaces.match_enclosed_volume`;
  the count-preserving iso-value leaves a tumour a few voxels across up to 10 % short).
* **Volume**: each remeshed surface is offset along its normals (skin vertices only for
  the outer one, so cut faces stay on their planes) back to the volume of its
  marching-cubes surface (:func:`~regtrack.model.remesh.restore_volume`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from regtrack.model.prepare import PreparedBreast
from regtrack.model.remesh import REMESH_TRIES, SurfaceCheck, check_surfaces, remesh, restore_volume
from regtrack.model.surfaces import (Surface, extract_surface, match_enclosed_volume, plane_field, slope_per_mm,
                                    smooth_levelset)

log = logging.getLogger(__name__)


@dataclass
class BreastSurfaces:
    """Remeshed boundary surfaces (LPS mm) and their checks."""

    outer: Surface
    tumours: list[Surface]
    tumour_voxel_mm3: list[float]
    checks: list[SurfaceCheck] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # empty when every check passed
    tries: int = 1
    info: dict = field(default_factory=dict)
    raw_outer: Surface | None = None  # marching-cubes outer surface (dense; nipple detection)


def surface_step(edge_mm: float, spacing: np.ndarray, configured: int = 0) -> int:
    """Marching-cubes step (voxels): the configured one, or ``round(L / (2.5 s))`` when 0,
    so the remesher starts from triangles a few times smaller than its target ``L``."""
    if configured > 0:
        return configured
    return int(max(1, round(edge_mm / (2.5 * float(np.mean(spacing))))))


def open_close(mask: np.ndarray, radius_mm: float, spacing: np.ndarray) -> np.ndarray:
    """Morphological closing then opening of ``mask`` with a ball of ``radius_mm``.

    Computed with Euclidean distance transforms (``dilate(M) = {d(., M) <= r}``,
    ``erode(M) = {d(., not M) > r}``), exact for any voxel spacing.  The array border
    does not erode (a body that leaves the crop continues beyond it).
    """
    if radius_mm <= 0:
        return mask
    sp = np.asarray(spacing, float)

    def dilate(m):
        return ndimage.distance_transform_edt(~m, sampling=sp) <= radius_mm

    def erode(m):
        return ndimage.distance_transform_edt(m, sampling=sp) > radius_mm

    closed = erode(dilate(mask)) | mask
    return dilate(erode(closed))


def outer_field(prep: PreparedBreast, *, smoothing_mm: float, feature_mm: float,
                rim_mm: float = 0.0) -> np.ndarray:
    """Level set of the outer surface: smoothed breast cut by every plane (positive inside).

    ``rim_mm`` > 0: each cut is a smooth minimum (:func:`smooth_min`, width ``rim_mm``)
    instead of the exact one, so the rim where the skin meets a cut face is rounded and a
    wedge of tissue thinner than about ``rim_mm`` between the skin and a cut plane (the
    lateral edge of a breast whose skin meets the tilted chest-wall plane at a few degrees,
    Pelicano exam 41 left) is shaved off; its remeshed triangles otherwise fold onto the
    cut face.  Cut faces stay exactly planar farther than ``rim_mm`` from the skin.
    """
    vol = prep.volume
    s = slope_per_mm(smoothing_mm)
    mask = open_close(prep.smooth_mask, feature_mm, vol.spacing)
    g = smooth_levelset(mask, smoothing_mm, vol.spacing, region=prep.inside, target_count=int(prep.breast.sum()))
    for p in prep.planes:
        pf = plane_field(vol.shape, vol.affine, p, s)
        g = smooth_min(g, pf, s * rim_mm) if rim_mm > 0 else np.minimum(g, pf)
    return g


ROUND_MM = 1.0  # width (mm) over which a tumour's trimmed rim is rounded


def smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (Quilez): ``min(a, b) - k q^2 / 4``, ``q = max(k - |a - b|, 0) / k``.

    Equal to ``min(a, b)`` where ``|a - b| >= k``; rounds the crease where a tumour is
    trimmed by the clearance (a sharp rim folds when it is remeshed).
    """
    q = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - 0.25 * k * q * q


def inner_distance(g: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Distance (mm) from each voxel centre inside ``g > 0`` to the region's boundary."""
    sp = np.asarray(spacing, float)
    return ndimage.distance_transform_edt(np.pad(g > 0, 1), sampling=sp)[1:-1, 1:-1, 1:-1] - 0.5 * float(np.mean(sp))


def tumour_fields(prep: PreparedBreast, d_out: np.ndarray, *, smoothing_mm: float | list[float],
                  clearance_mm: float, feature_mm: list[float] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(level set, affine of its sub-array) of every kept tumour, kept ``clearance_mm``
    inside the outer region (``d_out``: :func:`inner_distance` of the outer level set);
    ``smoothing_mm``: Gaussian sigma (mm), one for all or one per tumour; ``feature_mm``:
    closing/opening radius (mm) of each tumour mask."""
    vol = prep.volume
    sp = vol.spacing
    sigmas = _per_tumour(smoothing_mm, len(prep.tumours.kept))
    out = []
    for i, t in enumerate(prep.tumours.kept):
        sigma = sigmas[i]
        st = slope_per_mm(sigma)
        pad = np.ceil(3 * sigma / sp).astype(int) + 2
        r = feature_mm[i] if feature_mm else 0.0
        pd = pad + np.ceil(r / sp).astype(int)
        sl = tuple(slice(max(a.start - p, 0), min(a.stop + p, n)) for a, p, n in zip(t.slices, pd, vol.shape))
        m = prep.tumours.labelled[sl] == t.component
        ft = smooth_levelset(open_close(m, r, sp), sigma, sp, target_count=int(m.sum()))
        aff = vol.affine.copy()
        aff[:3, 3] = vol.index_to_world([a.start for a in sl])
        ft = match_enclosed_volume(ft, aff, float(m.sum()) * vol.voxel_volume)
        gt = smooth_min(ft, st * (d_out[sl] - clearance_mm), st * ROUND_MM)
        if gt.max() <= 0:  # a thin tumour right under the skin: halve the deepest gap
            c = 0.5 * float(d_out[sl][ft > 0].max(initial=0.0))
            log.warning("tumour %d lies within %.1f mm of the outer surface; clearance reduced to %.2f mm",
                        t.id, clearance_mm, c)
            gt = smooth_min(ft, st * (d_out[sl] - c), st * ROUND_MM)
        out.append((gt, aff))
    return out


def _per_tumour(value: float | list[float], n: int) -> list[float]:
    """A scalar setting repeated for ``n`` tumours, or the per-tumour list itself."""
    if isinstance(value, (int, float)):
        return [float(value)] * n
    if len(value) != n:
        raise ValueError(f"tumour_smoothing_mm: {len(value)} values for {n} tumours")
    return [float(v) for v in value]


def make_surfaces(prep: PreparedBreast, *, edge_mm: float, tumour_edges_mm: list[float],
                  smoothing_mm: float, tumour_smoothing_mm: float | list[float], clearance_mm: float,
                  feature_fraction: float, small_angle_deg: float, step_vox: int = 0, rim_mm: float = 0.0,
                  tries: int = len(REMESH_TRIES), nipple_mm: np.ndarray | None = None) -> BreastSurfaces:
    """Checked, remeshed outer and tumour surfaces of ``prep`` (see the module docstring).

    Parameters
    ----------
    edge_mm, tumour_edges_mm : float, list of float
        Target triangle edge lengths (mm) of the outer surface and of each tumour.
    smoothing_mm, tumour_smoothing_mm : float, float or list of float
        Gaussian sigmas (mm) of the level sets (tumours: one for all, or one per tumour).
    clearance_mm : float
        Smallest gap (mm) between a tumour and the outer surface's level set (plus the
        chord allowance of :data:`REMESH_TRIES`).
    feature_fraction : float
        Radius of the closing/opening ball as a fraction of ``edge_mm``.
    small_angle_deg : float
        Triangles with a smaller angle fail the check.
    step_vox : int
        Marching-cubes step (0: automatic, :func:`surface_step`).
    rim_mm : float
        Width (mm) of the rounded rim between the skin and the cut faces (:func:`outer_field`;
        0: a sharp rim).
    tries : int
        Remeshing settings tried (first ones of ``REMESH_TRIES``) before giving up.
    nipple_mm : (3,) array, optional
        Nipple point (LPS mm) on the surface: the nearest skin vertex of the remeshed
        outer surface is moved onto it, so the model has a node at the nipple however
        coarse the mesh (at 5,000 nodes the nearest node was 4 mm away).
    """
    vol = prep.volume
    sp = vol.spacing
    g = outer_field(prep, smoothing_mm=smoothing_mm, feature_mm=feature_fraction * edge_mm, rim_mm=rim_mm)
    step = surface_step(edge_mm, sp, step_vox)
    snap = 0.5 * step * float(np.mean(sp))
    raw_outer = extract_surface(g, vol.affine, step=step, planes=tuple(prep.planes), snap_mm=0.0, relax_iterations=0)
    d_out = inner_distance(g, sp)
    raw_t: dict[tuple[float, float], list[Surface]] = {}
    best = None
    for k, (iters, fac, allow, tfeat) in enumerate(REMESH_TRIES[: max(1, tries)]):
        clear = clearance_mm + allow * edge_mm
        tkey = (clear, tfeat)
        if tkey not in raw_t:
            raw_t[tkey] = [extract_surface(gt, aff, step=surface_step(e, sp), relax_iterations=0)
                           for (gt, aff), e in zip(tumour_fields(prep, d_out, smoothing_mm=tumour_smoothing_mm, clearance_mm=clear,
                                                                feature_mm=[tfeat * feature_fraction * x for x in tumour_edges_mm]),
                                                   tumour_edges_mm)]
        outer = remesh(raw_outer, edge_mm=edge_mm * fac, iterations=iters, planes=tuple(prep.planes), snap_mm=snap)
        on = np.zeros(len(outer.verts), bool)
        for p in prep.planes:
            on |= np.abs(p.distance(outer.verts)) < 1e-6
        outer = restore_volume(outer, raw_outer.volume, movable=~on)
        if nipple_mm is not None:
            skin = np.nonzero(~on)[0]
            j = skin[np.argmin(np.linalg.norm(outer.verts[skin] - nipple_mm, axis=1))]
            outer.verts[j] = nipple_mm
        tums = [restore_volume(remesh(s, edge_mm=e * fac, iterations=iters), s.volume)
                for s, e in zip(raw_t[tkey], tumour_edges_mm)]
        chk = check_surfaces([outer] + tums, small_angle_deg=small_angle_deg, planes=tuple(prep.planes))
        problems = [f"{'outer' if i == 0 else f'tumour {i}'} surface: {p}"
                    for i, c in enumerate(chk) for p in c.problems(min_angle_deg=small_angle_deg)]
        res = BreastSurfaces(outer, tums, [t.volume_mm3 for t in prep.tumours.kept], chk, problems, k + 1,
                             {"marching_cubes_step_vox": step, "snap_mm": snap, "iterations": iters,
                              "edge_factor": fac, "feature_radius_mm": feature_fraction * edge_mm,
                              "tumour_clearance_mm": clear, "tumour_feature_radius_factor": tfeat * feature_fraction},
                             raw_outer)
        if not problems:
            return res
        log.info("remeshing try %d (%d iterations, edge x %.2f, clearance %.2f mm): %s", k + 1, iters, fac, clear,
                 "; ".join(problems))
        if best is None or len(problems) < len(best.problems):
            best = res
    best.tries = min(len(REMESH_TRIES), max(1, tries))
    return best


__all__ = ["BreastSurfaces", "make_surfaces", "surface_step", "open_close", "outer_field", "tumour_fields"]
