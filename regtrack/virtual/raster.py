"""Vectorised rasterisation of projected triangles on a regular 2-D grid (mm).

A pixel belongs to a triangle when its *centre* lies inside it.  Pixels exactly on an
edge are given to exactly one of the two triangles sharing that edge (a half-open
"owner" rule evaluated with edge functions computed in one canonical direction per
edge), so a tiling of triangles covers every pixel once: signed sums over front and
back faces (line integrals, :mod:`regtrack.virtual.xray`) count no pixel twice.

Edge function of the directed edge ``u -> v`` at pixel centre ``p``:

.. math:: E_{uv}(p) = (v - u) \\times (p - u)

(2-D cross product).  For a counter-clockwise triangle ``(a, b, c)`` the barycentric
weight of vertex ``a`` is :math:`E_{bc}(p) / (2A)`, with ``A`` the triangle area.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit

#: Largest number of (triangle, pixel) candidates handled at once (memory bound).
CHUNK_CANDIDATES = 2_000_000


@dataclass(frozen=True)
class Grid:
    """A regular pixel grid in the canonical 2-D frame (mm).

    Pixel ``(row, col)`` has its centre at ``(x, y) = origin + (col * spacing, row * spacing)``
    (the convention of :class:`regtrack.views.MammogramView`, square pixels).
    """

    origin: tuple[float, float]
    spacing: float
    shape: tuple[int, int]

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) pixel-centre coordinates (mm) of columns and rows."""
        h, w = self.shape
        return (self.origin[0] + np.arange(w) * self.spacing,
                self.origin[1] + np.arange(h) * self.spacing)

    @property
    def pixel_area(self) -> float:
        """Area of one pixel (mm^2)."""
        return self.spacing * self.spacing


def grid_around(xy: np.ndarray, *, spacing: float, margin: int = 3) -> Grid:
    """Smallest grid with pixel centres on multiples of ``spacing`` covering ``xy`` (mm)
    plus ``margin`` pixels on every side."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    lo = np.floor(xy.min(0) / spacing) - margin
    hi = np.ceil(xy.max(0) / spacing) + margin
    shape = (int(hi[1] - lo[1]) + 1, int(hi[0] - lo[0]) + 1)
    return Grid((float(lo[0] * spacing), float(lo[1] * spacing)), float(spacing), shape)


def rasterise(points: np.ndarray, faces: np.ndarray, grid: Grid, *,
              values: np.ndarray | None = None, weights: np.ndarray | None = None,
              post: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Accumulate triangles on ``grid``.

    Parameters
    ----------
    points : (N, 2) float
        Projected vertex coordinates (mm).
    faces : (T, 3) int
        Triangles (any orientation; degenerate ones are skipped).
    grid : Grid
    values : (N,) float, optional
        Vertex values, linearly interpolated inside each triangle (e.g. depth, mm).
    weights : (T,) float, optional
        Per-triangle factor of the accumulated values (e.g. +1 exit / -1 entry face).
    post : callable, optional
        Applied to interpolated values before weighting (e.g. a depth change of variable).

    Returns
    -------
    count : (H, W) int
        Number of triangles covering each pixel centre.
    acc : (H, W) float
        Sum over covering triangles of ``weight * post(interpolated value)`` (zeros when
        ``values`` is None).
    """
    points = np.asarray(points, float)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    h, w = grid.shape
    count = np.zeros(h * w, np.int64)
    acc = np.zeros(h * w, float)
    if len(faces) == 0:
        return count.reshape(h, w), acc.reshape(h, w)
    wts = np.ones(len(faces)) if weights is None else np.asarray(weights, float)
    p = points[faces]
    area2 = ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
             - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
    keep = np.abs(area2) > 1e-12 * max(grid.spacing, 1.0) ** 2
    faces, p, area2, wts = faces[keep], p[keep], area2[keep], wts[keep]
    cw = area2 < 0  # make every triangle counter-clockwise (swap vertices 1 and 2)
    faces = faces.copy()
    faces[cw, 1], faces[cw, 2] = faces[cw, 2], faces[cw, 1].copy()
    p = points[faces]
    area2 = np.abs(area2)
    ox, oy = grid.origin
    s = grid.spacing
    c0 = np.maximum(np.ceil((p[:, :, 0].min(1) - ox) / s), 0).astype(np.int64)
    c1 = np.minimum(np.floor((p[:, :, 0].max(1) - ox) / s), w - 1).astype(np.int64)
    r0 = np.maximum(np.ceil((p[:, :, 1].min(1) - oy) / s), 0).astype(np.int64)
    r1 = np.minimum(np.floor((p[:, :, 1].max(1) - oy) / s), h - 1).astype(np.int64)
    nc = np.maximum(c1 - c0 + 1, 0)
    nr = np.maximum(r1 - r0 + 1, 0)
    ncand = nc * nr
    csum = np.cumsum(ncand)
    start = 0
    while start < len(faces):
        base = csum[start - 1] if start else 0
        stop = int(np.searchsorted(csum, base + CHUNK_CANDIDATES, side="right"))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        _accumulate(points, faces[sl], area2[sl], wts[sl], c0[sl], r0[sl], nc[sl], ncand[sl],
                    grid, values, post, count, acc)
        start = stop
    return count.reshape(h, w), acc.reshape(h, w)


@njit(cache=True, nogil=True)
def _covered(points, faces, c0, r0, nc, ncand, ox, oy, s, width):  # pragma: no cover (JIT)
    """Pixels whose centre lies in each triangle (owner rule of the module docstring).

    Returns the flat pixel index, the triangle and the three edge functions (barycentric
    numerators, opposite vertices 0, 1, 2) of every covered (triangle, pixel) pair, in
    triangle order and row-major within a triangle's bounding box."""
    total = 0
    for t in range(len(faces)):
        total += ncand[t]
    idx = np.empty(total, np.int64)
    tri = np.empty(total, np.int64)
    bary = np.empty((total, 3))
    n = 0
    e = np.empty(3)
    ax, ay, ex, ey = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    sign = np.empty(3)
    owned = np.zeros(3, np.bool_)
    for t in range(len(faces)):
        for k in range(3):  # edge opposite vertex k: (k+1 -> k+2), evaluated canonically
            iu = faces[t, (k + 1) % 3]
            iv = faces[t, (k + 2) % 3]
            a, b = (iv, iu) if iu > iv else (iu, iv)
            ax[k], ay[k] = points[a, 0], points[a, 1]
            ex[k], ey[k] = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1]
            sign[k] = -1.0 if iu > iv else 1.0
            dx = points[iv, 0] - points[iu, 0]
            dy = points[iv, 1] - points[iu, 1]
            owned[k] = dy > 0 or (dy == 0 and dx > 0)
        for q in range(ncand[t]):
            col = c0[t] + q % nc[t]
            row = r0[t] + q // nc[t]
            px = ox + col * s
            py = oy + row * s
            inside = True
            for k in range(3):
                ek = sign[k] * (ex[k] * (py - ay[k]) - ey[k] * (px - ax[k]))
                if not (ek > 0 or (ek == 0 and owned[k])):
                    inside = False
                    break
                e[k] = ek
            if inside:
                idx[n] = row * width + col
                tri[n] = t
                bary[n, 0], bary[n, 1], bary[n, 2] = e[0], e[1], e[2]
                n += 1
    return idx[:n], tri[:n], bary[:n]


def _accumulate(points, faces, area2, wts, c0, r0, nc, ncand, grid, values, post, count, acc):
    if int(ncand.sum()) == 0:
        return
    idx, tri, bary = _covered(points, faces, c0, r0, nc, ncand, float(grid.origin[0]),
                              float(grid.origin[1]), float(grid.spacing), int(grid.shape[1]))
    count += np.bincount(idx, minlength=count.size)
    if values is None:
        return
    v = np.asarray(values, float)[faces[tri]]
    val = sum(bary[:, k] * v[:, k] for k in range(3)) / area2[tri]
    if post is not None:
        val = post(val)
    acc += np.bincount(idx, weights=val * wts[tri], minlength=acc.size)
