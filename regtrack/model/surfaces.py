"""Smooth closed surfaces from voxel masks (marching cubes on smoothed level sets).

A mask ``M`` is smoothed with a Gaussian ``G_sigma`` and the iso-level ``t`` is chosen so
that the smoothed region holds exactly as many voxels as the mask (volume preservation):

.. math:: f = G_\\sigma * M - t, \\qquad \\#\\{f > 0\\} = \\#\\{M\\}.

Cuts by planes are intersections of level sets, ``g = min(f, s\\,d_1, s\\,d_2, ...)`` with
``d_p`` the signed distance (mm) to plane ``p`` and ``s = 1 / (\\sigma \\sqrt{2\\pi})`` the
slope of ``f`` across the smoothed boundary (mm^-1), so ``g`` is close to a scaled signed
distance everywhere and the cut faces stay exactly flat.  Marching cubes (Lorensen & Cline
1987, scikit-image) extracts ``g = 0``; vertices closer than half a voxel to a cut plane
are projected onto it so the cut faces are planar and their rims are sharp features.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse

from regtrack.model.chestwall import Plane

log = logging.getLogger(__name__)


@dataclass
class Surface:
    """Closed triangle surface in LPS mm."""

    verts: np.ndarray  # (n, 3)
    faces: np.ndarray  # (m, 3)

    @property
    def area(self) -> float:
        p = self.verts[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())

    @property
    def volume(self) -> float:
        """Enclosed volume (mm^3, divergence theorem; sign follows the orientation)."""
        p = self.verts[self.faces]
        return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def slope_per_mm(sigma_mm: float) -> float:
    """Slope of a Gaussian-smoothed unit step at its 0.5 level (mm^-1)."""
    return 1.0 / (max(sigma_mm, 0.5) * np.sqrt(2.0 * np.pi))


def smooth_levelset(mask: np.ndarray, sigma_mm: float, spacing: np.ndarray, *,
                    region: np.ndarray | None = None, target_count: int | None = None) -> np.ndarray:
    """Volume-preserving smoothed level set of ``mask`` (positive inside).

    ``target_count`` voxels of ``region`` (default: the whole array; count default: the
    mask's voxels in ``region``) end up with a positive value.
    """
    f = mask.astype(np.float32)
    if sigma_mm > 0:
        f = ndimage.gaussian_filter(f, sigma=sigma_mm / np.asarray(spacing, float), mode="nearest",
                                    truncate=3.0)
    vals = f[region] if region is not None else f.ravel()
    if target_count is None:
        target_count = int(np.count_nonzero(mask[region] if region is not None else mask))
    if sigma_mm <= 0 or target_count <= 0 or target_count >= vals.size:
        return f - 0.5
    k = vals.size - target_count
    lo = np.partition(vals, [k - 1, k])
    t = 0.5 * (float(lo[k - 1]) + float(lo[k]))
    t = min(max(t, 0.05), 0.95)
    return f - np.float32(t)


def match_enclosed_volume(f: np.ndarray, affine: np.ndarray, target_mm3: float, *,
                          rtol: float = 1e-3) -> np.ndarray:
    """Shift the level set ``f`` (positive inside) by a constant so that its marching-cubes
    surface (:func:`extract_surface`, step 1, largest piece) encloses ``target_mm3``.

    :func:`smooth_levelset` keeps the *count* of voxel centres inside, and on an object a
    few voxels across the surface through them encloses less: a 2.5-mm sphere (81 voxels of
    1 mm^3) gives a marching-cubes volume of 72.9 mm^3, 10 % short, whatever the element
    size.  The enclosed volume decreases monotonically with the shift ``c``, so ``c`` is
    found by Brent's method on ``V(c) = target`` within ``(min f, max f)``; a target
    outside the reachable range takes the nearest end.  ``rtol``: relative volume tolerance.
    """
    from scipy.optimize import brentq

    target = float(target_mm3)
    if target <= 0 or not (f > 0).any():
        return f

    def excess(c: float) -> float:
        try:
            return abs(extract_surface(f - np.float32(c), affine, step=1, relax_iterations=0).volume) / target - 1.0
        except (ValueError, RuntimeError):  # nothing left inside
            return -1.0

    e0 = excess(0.0)
    if abs(e0) <= rtol:
        return f
    span = float(f.max() - f.min())
    lo, hi = (float(f.min()) + 1e-3 * span, 0.0) if e0 < 0 else (0.0, float(f.max()) - 1e-3 * span)
    elo, ehi = (excess(lo), e0) if e0 < 0 else (e0, excess(hi))
    if elo < 0:
        c = lo
    elif ehi > 0:
        c = hi
    else:
        c = brentq(excess, lo, hi, xtol=1e-6 * span, rtol=1e-6, maxiter=40)
    return f - np.float32(c)


def plane_field(shape: tuple[int, ...], affine: np.ndarray, plane: Plane, scale: float) -> np.ndarray:
    """``scale * plane.distance`` at every voxel centre (float32 array of ``shape``)."""
    a = affine[:3, :3].T @ plane.normal  # d(distance)/d(index)
    b = affine[:3, 3] @ plane.normal - plane.offset
    i, j, k = (np.arange(n, dtype=np.float32) for n in shape)
    return (scale * (a[0] * i[:, None, None] + a[1] * j[None, :, None] + a[2] * k[None, None, :] + b)).astype(np.float32)


def largest_component(surf: Surface) -> Surface:
    """Keep the largest connected piece (by face count) of a triangle surface."""
    n = len(surf.verts)
    f = surf.faces
    adj = sparse.coo_matrix((np.ones(3 * len(f)), (f.ravel(), np.roll(f, 1, axis=1).ravel())), shape=(n, n))
    ncomp, lab = sparse.csgraph.connected_components(adj, directed=False)
    if ncomp == 1:
        return surf
    flab = lab[f[:, 0]]
    keep = np.bincount(flab).argmax()
    faces = f[flab == keep]
    used = np.unique(faces)
    remap = -np.ones(n, np.int64)
    remap[used] = np.arange(len(used))
    dropped = len(f) - len(faces)
    log.debug("surface: dropped %d faces in %d small pieces", dropped, ncomp - 1)
    return Surface(surf.verts[used], remap[faces])


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    p = verts[faces]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    vn = np.zeros_like(verts)
    for c in range(3):
        np.add.at(vn, faces[:, c], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def relax(surf: Surface, *, planes: tuple[Plane, ...] = (), iterations: int = 30,
          step: float = 0.3, tol_mm: float = 1e-3) -> Surface:
    """Tangential Laplacian relaxation, which spreads marching-cubes slivers out.

    Each pass moves every vertex by ``step`` times the tangential part of its umbrella
    vector ``u = mean(neighbours) - x``, ``x <- x + step (u - (u.n) n)``; vertices on a
    cut plane move within that plane, so cut faces stay flat.  The shape moves by far
    less than a voxel (the normal component is removed).
    """
    v = surf.verts.copy()
    f = surf.faces
    n = len(v)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    adj = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    adj.data[:] = 1.0
    deg = np.asarray(adj.sum(axis=1)).ravel()
    on = [np.abs(p.distance(v)) < tol_mm for p in planes]
    n_on = np.sum(on, axis=0) if on else np.zeros(n, int)
    for _ in range(iterations):
        u = adj @ v / deg[:, None] - v
        nrm = vertex_normals(v, f)
        free = np.ones(n, bool)
        for p, m in zip(planes, on):
            free &= ~m
        ut = u - (u * nrm).sum(axis=1, keepdims=True) * nrm
        for p, m in zip(planes, on):
            ut[m] = u[m] - np.outer(u[m] @ p.normal, p.normal)
        ut[n_on > 1] = 0.0
        v += step * ut
    return Surface(v, f)


def extract_surface(g: np.ndarray, affine: np.ndarray, *, step: int = 1,
                    planes: tuple[Plane, ...] = (), snap_mm: float = 0.5,
                    relax_iterations: int = 30) -> Surface:
    """Marching-cubes surface ``g = 0`` (``g`` positive inside) in LPS mm.

    The array is padded with a negative value so the surface is closed (also with
    ``step > 1``).  Vertices within
    ``snap_mm`` of a plane are projected onto it.  Faces are oriented with outward normals.
    ``relax_iterations`` passes of :func:`relax` follow (0: none, when the surface is
    remeshed afterwards).
    """
    from skimage import measure

    # one negative layer before and at least one after, so that (n - 1) is a multiple of
    # the step: marching cubes with step > 1 skips a last partial layer (open surface)
    after = [1 + (-(n + 1)) % step for n in g.shape]
    pad = np.pad(g, [(1, a) for a in after], mode="constant", constant_values=-1.0)
    # a value exactly at the level puts a vertex on a grid point shared by several cubes;
    # skimage then drops the degenerate triangles and leaves open/non-manifold edges
    pad[pad == 0.0] = -1e-6
    verts, faces, _, _ = measure.marching_cubes(pad, level=0.0, step_size=step, allow_degenerate=False)
    verts = verts - 1.0
    xyz = verts @ affine[:3, :3].T + affine[:3, 3]
    surf = largest_component(Surface(xyz, faces.astype(np.int64)))
    xyz = surf.verts
    for p in planes:
        d = p.distance(xyz)
        near = np.abs(d) < snap_mm
        xyz[near] = p.project(xyz[near])
    if surf.volume < 0:
        surf.faces = surf.faces[:, ::-1].copy()
    if relax_iterations <= 0:
        return surf
    return relax(surf, planes=planes, iterations=relax_iterations)
