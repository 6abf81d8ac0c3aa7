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


def _edge(pu, pv, px, py, flip):
    """Canonical edge function E_{uv}; ``flip`` negates it (edge traversed v -> u)."""
    e = (pv[:, 0] - pu[:, 0]) * (py - pu[:, 1]) - (pv[:, 1] - pu[:, 1]) * (px - pu[:, 0])
    return np.where(flip, -e, e)


def _owned(d: np.ndarray) -> np.ndarray:
    """Half-open owner rule for a directed edge vector ``d`` (exactly one of d, -d owns)."""
    return (d[:, 1] > 0) | ((d[:, 1] == 0) & (d[:, 0] > 0))


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


def _accumulate(points, faces, area2, wts, c0, r0, nc, ncand, grid, values, post, count, acc):
    total = int(ncand.sum())
    if total == 0:
        return
    tri = np.repeat(np.arange(len(faces)), ncand)
    local = np.arange(total) - np.repeat(np.cumsum(ncand) - ncand, ncand)
    cols = c0[tri] + local % np.maximum(nc[tri], 1)
    rows = r0[tri] + local // np.maximum(nc[tri], 1)
    px = grid.origin[0] + cols * grid.spacing
    py = grid.origin[1] + rows * grid.spacing
    f = faces[tri]
    inside = np.ones(total, bool)
    bary = []
    for k in range(3):  # edge opposite vertex k: (k+1 -> k+2)
        iu, iv = f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        flip = iu > iv
        a = np.where(flip, iv, iu)
        b = np.where(flip, iu, iv)
        e = _edge(points[a], points[b], px, py, flip)
        d = points[iv] - points[iu]
        inside &= (e > 0) | ((e == 0) & _owned(d))
        bary.append(e)
    idx = rows[inside] * grid.shape[1] + cols[inside]
    count += np.bincount(idx, minlength=count.size)
    if values is None:
        return
    v = np.asarray(values, float)[f[inside]]
    a2 = area2[tri[inside]]
    val = sum(bary[k][inside] * v[:, k] for k in range(3)) / a2
    if post is not None:
        val = post(val)
    acc += np.bincount(idx, weights=val * wts[tri[inside]], minlength=acc.size)
