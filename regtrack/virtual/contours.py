"""Contours of rasterised regions and the open (chest-wall-free) breast contour."""

from __future__ import annotations

import logging

import numpy as np

from regtrack.virtual.raster import Grid

log = logging.getLogger(__name__)


def polygon_area(poly: np.ndarray) -> float:
    """Signed shoelace area (mm^2) of a closed polygon (first point not repeated)."""
    x, y = np.asarray(poly, float).T
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def mask_contours(mask: np.ndarray, grid: Grid) -> list[np.ndarray]:
    """Closed outer contours (mm) of a binary mask, largest area first.

    Holes are filled first; each contour runs through the mid-points between inside
    and outside pixel centres (marching squares at level 0.5), so it lies within half
    a pixel of the true boundary of the rasterised region.  Contours are returned
    counter-clockwise in the (x, y) plane (positive shoelace area), last point not
    repeated.
    """
    from scipy import ndimage
    from skimage import measure

    filled = ndimage.binary_fill_holes(np.asarray(mask, bool))
    padded = np.pad(filled, 1).astype(float)
    out = []
    for c in measure.find_contours(padded, 0.5):
        if len(c) < 4:
            continue
        c = c[:-1] if np.allclose(c[0], c[-1]) else c
        xy = np.stack([grid.origin[0] + (c[:, 1] - 1) * grid.spacing,
                       grid.origin[1] + (c[:, 0] - 1) * grid.spacing], 1)
        if polygon_area(xy) < 0:
            xy = xy[::-1]
        out.append(xy)
    out.sort(key=polygon_area, reverse=True)
    return out


def open_contour(closed: np.ndarray, on_chest_wall: np.ndarray) -> np.ndarray:
    """The longest cyclic run of contour points *not* on the chest wall.

    Parameters
    ----------
    closed : (M, 2) float
        Closed contour (mm), last point not repeated.
    on_chest_wall : (M,) bool
        Points on the chest-wall side.

    Returns
    -------
    (K, 2) float
        Open polyline from one chest-wall end to the other, starting at the end with
        the smaller ``y`` (top of the canonical image).
    """
    closed = np.asarray(closed, float)
    flags = np.asarray(on_chest_wall, bool)
    if flags.all():
        return closed[:0]
    if not flags.any():
        return closed.copy()
    # roll so that the contour starts right after a chest-wall point
    first_cw = int(np.argmax(flags))
    order = np.roll(np.arange(len(closed)), -(first_cw + 1))
    f = flags[order]
    # runs of False in f
    best_len, best_start, run_start = 0, 0, None
    for i, v in enumerate(np.append(f, True)):
        if not v and run_start is None:
            run_start = i
        elif v and run_start is not None:
            if i - run_start > best_len:
                best_len, best_start = i - run_start, run_start
            run_start = None
    seg = closed[order[best_start:best_start + best_len]]
    if seg[0, 1] > seg[-1, 1]:
        seg = seg[::-1]
    return seg


def chest_wall_flags(contour: np.ndarray, chest_wall_xy: np.ndarray, *, tol: float) -> np.ndarray:
    """Contour points (mm) within ``tol`` mm of the chest-wall sample points (mm)."""
    from scipy.spatial import cKDTree

    if len(chest_wall_xy) == 0:
        return np.zeros(len(contour), bool)
    d, _ = cKDTree(chest_wall_xy).query(contour, distance_upper_bound=tol)
    return np.isfinite(d)


def sample_triangle_edges(points: np.ndarray, faces: np.ndarray, *, step: float) -> np.ndarray:
    """Points (mm) along every edge of projected triangles, at most ``step`` apart."""
    if len(faces) == 0:
        return np.zeros((0, 2))
    p = np.asarray(points, float)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, 1), axis=0)
    a, b = p[e[:, 0]], p[e[:, 1]]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step).astype(int), 1)
    idx = np.repeat(np.arange(len(e)), n + 1)
    t = (np.arange(len(idx)) - np.repeat(np.cumsum(n + 1) - (n + 1), n + 1)) / np.repeat(n, n + 1)
    return a[idx] + (b[idx] - a[idx]) * t[:, None]
