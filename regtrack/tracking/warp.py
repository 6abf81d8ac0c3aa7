"""The MRI warped into a compressed state: the label map (or the MR series) resampled
through the finite-element deformation (Chung et al. 2008).

Each output voxel centre ``p`` (LPS, mm) is pulled back through the inverse map of the
deformed mesh (:class:`~regtrack.tracking.deformation.DeformationMap`):
``P = \\varphi^{-1}(p)``, and takes the input's value at ``P``,

.. math::

    I'(p) = I(\\varphi^{-1}(p)) \\quad (p \\text{ inside the deformed mesh}), \\qquad
    I'(p) = \\text{background} \\quad \\text{otherwise},

nearest-neighbour for a label map (labels are never blended), trilinear for an
intensity image (:func:`scipy.ndimage.map_coordinates`).  Outside the breast model (the
other breast, the torso, air) the output is background: the model holds only the breast.

The voxels are found element by element (scan conversion): for each deformed tetrahedron,
the voxel centres of its bounding box get their barycentric coordinates ``mu`` in it, and
those with ``min mu >= -1e-9`` take ``\\varphi^{-1}(p) = \\sum_k \\mu_k X_k``.  A dense grid
visits each (element, voxel of its box) pair once, with no point search: 2.6M candidate
voxels of the phantom's label map in 2 s, where locating them one by one
(:class:`~regtrack.tracking.locate.TetLocator`, built for a few points) took minutes,
most of it proving that the voxels outside the breast lie in no element.  Affine maps
keep barycentric coordinates, so the test runs in voxel-index space.

Output grid: the input's voxel spacing and orientation, extended (whole voxels) to hold
the deformed breast, so the result shares the MRI's frame of reference and overlays a
compressed MRI of the same session.  The extension keeps voxel ``(0, 0, 0)`` of the input
at index ``offset``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from numba import njit

from regtrack.imaging.volume import Volume
from regtrack.tracking.deformation import DeformationMap

log = logging.getLogger(__name__)


@dataclass
class WarpedVolume:
    """A warped volume and how its grid relates to the input's.

    Attributes
    ----------
    volume : Volume
        Same class as the input (``LabelVolume`` / ``ImageVolume``), new data and affine.
    offset : (3,) int
        Index of the input's voxel (0, 0, 0) in the output grid.
    inside : int
        Output voxels inside the deformed breast model.
    """

    volume: Volume
    offset: np.ndarray
    inside: int


def _grid(vol: Volume, points_lps: np.ndarray, margin: int) -> tuple[np.ndarray, tuple[int, ...]]:
    """Offset and shape of the input grid extended to hold ``points_lps`` (+ margin voxels)."""
    ijk = _to_index(vol.affine, points_lps)
    lo = np.minimum(np.floor(ijk.min(axis=0)).astype(int) - margin, 0)
    hi = np.maximum(np.ceil(ijk.max(axis=0)).astype(int) + margin + 1, np.array(vol.shape))
    return -lo, tuple(int(v) for v in hi - lo)


def _to_index(affine: np.ndarray, lps: np.ndarray) -> np.ndarray:
    """(M, 3) LPS mm -> continuous voxel indices (M, 3)."""
    inv = np.linalg.inv(affine)
    return lps @ inv[:3, :3].T + inv[:3, 3]


def warp_volume(vol: Volume, dmap: DeformationMap, *, order: int | None = None,
                background: float = 0.0, margin: int = 2) -> WarpedVolume:
    """Resample ``vol`` through the deformation ``dmap`` (see the module docstring).

    Parameters
    ----------
    vol : LabelVolume or ImageVolume
        The MRI label map or series, voxel-to-LPS affine.
    dmap : DeformationMap
        The simulated compression (reference = the MRI's prone state).
    order : {0, 1}, optional
        Interpolation: 0 nearest (default for integer data), 1 trilinear (default for
        float data).
    background : float
        Value outside the deformed breast model.
    margin : int
        Voxels kept around the deformed model when the grid is extended.
    """
    from scipy.ndimage import map_coordinates

    data = np.asarray(vol.data)
    if order is None:
        order = 0 if np.issubdtype(data.dtype, np.integer) else 1
    deformed_lps = dmap.frame.to_patient(dmap.deformed)
    offset, shape = _grid(vol, deformed_lps, margin)
    affine = vol.affine.copy()
    affine[:3, 3] = vol.affine[:3, :3] @ (-offset) + vol.affine[:3, 3]
    out = np.full(shape, background, dtype=data.dtype if order == 0 else np.float32)
    # deformed nodes in output-voxel indices, reference nodes in input-voxel indices; the
    # pulled-back positions are kept for the deformed model's bounding box only
    x_idx = _to_index(affine, deformed_lps)
    lo = np.maximum(np.floor(x_idx.min(axis=0)).astype(int), 0)
    hi = np.minimum(np.ceil(x_idx.max(axis=0)).astype(int) + 1, np.array(shape))
    X_src = _to_index(vol.affine, dmap.frame.to_patient(dmap.reference))
    src = np.full(tuple(int(v) for v in hi - lo) + (3,), np.nan)
    _scan_convert(x_idx - lo, np.asarray(dmap.tets, np.int64), X_src, src, 1e-9)
    ok = np.isfinite(src[..., 0])
    inside = int(ok.sum())
    if inside:
        box = out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]  # a view: filled in place
        box[ok] = map_coordinates(data, src[ok].T, order=order, mode="constant",
                                  cval=background, prefilter=False)
    log.info("warped %s: %d voxels inside the deformed breast, grid %s (offset %s)",
             type(vol).__name__, inside, shape, offset.tolist())
    return WarpedVolume(type(vol)(data=out, affine=affine), offset, inside)


@njit(cache=True)
def _scan_convert(x_idx, tets, X_src, src, tol):  # pragma: no cover - compiled
    """For every tet (nodes ``x_idx``, output-voxel indices) and every voxel centre of its
    bounding box inside it: ``src[i, j, k] = sum_k mu_k X_src[node_k]`` (first tet wins)."""
    for e in range(tets.shape[0]):
        a, b, c, d = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        t = np.empty((3, 3))
        for r in range(3):
            t[r, 0] = x_idx[b, r] - x_idx[a, r]
            t[r, 1] = x_idx[c, r] - x_idx[a, r]
            t[r, 2] = x_idx[d, r] - x_idx[a, r]
        det = (t[0, 0] * (t[1, 1] * t[2, 2] - t[1, 2] * t[2, 1])
               - t[0, 1] * (t[1, 0] * t[2, 2] - t[1, 2] * t[2, 0])
               + t[0, 2] * (t[1, 0] * t[2, 1] - t[1, 1] * t[2, 0]))
        scale = max(abs(t.max()), abs(t.min())) ** 3
        if abs(det) <= 1e-12 * scale:
            continue  # degenerate: its neighbours cover its (zero) volume
        inv = np.linalg.inv(t)
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for r in range(3):
            m0 = min(x_idx[a, r], x_idx[b, r], x_idx[c, r], x_idx[d, r])
            m1 = max(x_idx[a, r], x_idx[b, r], x_idx[c, r], x_idx[d, r])
            lo[r] = max(int(np.ceil(m0 - 1e-9)), 0)
            hi[r] = min(int(np.floor(m1 + 1e-9)), src.shape[r] - 1)
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                for k in range(lo[2], hi[2] + 1):
                    if not np.isnan(src[i, j, k, 0]):
                        continue
                    dx = i - x_idx[a, 0]
                    dy = j - x_idx[a, 1]
                    dz = k - x_idx[a, 2]
                    l1 = inv[0, 0] * dx + inv[0, 1] * dy + inv[0, 2] * dz
                    l2 = inv[1, 0] * dx + inv[1, 1] * dy + inv[1, 2] * dz
                    l3 = inv[2, 0] * dx + inv[2, 1] * dy + inv[2, 2] * dz
                    l0 = 1.0 - l1 - l2 - l3
                    if min(l0, l1, l2, l3) < -tol:
                        continue
                    for r in range(3):
                        src[i, j, k, r] = (l0 * X_src[a, r] + l1 * X_src[b, r]
                                           + l2 * X_src[c, r] + l3 * X_src[d, r])
