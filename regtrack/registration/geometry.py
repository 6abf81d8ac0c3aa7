"""2-D contour geometry: resampling, rigid rotation about a point, closest points, and the
pairing of virtual and real outlines."""

from __future__ import annotations

import numpy as np


def rotation(theta_deg: float) -> np.ndarray:
    """2x2 rotation by ``theta_deg`` (deg): ``[[cos, -sin], [sin, cos]]`` in the (x, y) frame.

    With the canonical frame's ``y`` pointing down, a positive angle turns the image
    clockwise on screen.
    """
    t = np.deg2rad(theta_deg)
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s], [s, c]])


def rotate_about(xy: np.ndarray, centre: np.ndarray, theta_deg: float) -> np.ndarray:
    """Rotate (M, 2) points (mm) by ``theta_deg`` about ``centre`` (mm)."""
    xy = np.asarray(xy, float)
    return (xy - centre) @ rotation(theta_deg).T + centre


def resample(poly: np.ndarray, spacing: float, *, closed: bool) -> np.ndarray:
    """Points at equal arc-length ``spacing`` (mm) along a polyline.

    An open polyline keeps both end points (the spacing is adjusted to fit exactly); a
    closed one is sampled around its perimeter, last point not repeated.
    """
    p = np.asarray(poly, float)
    if closed:
        p = np.vstack([p, p[:1]])
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 0])
    p = p[keep]
    s = np.concatenate([[0.0], np.cumsum(seg[seg > 0])])
    total = s[-1]
    if total == 0:
        return p[:1].copy()
    n = max(int(np.ceil(total / spacing)), 2 if not closed else 3)
    t = np.linspace(0.0, total, n + 1)
    if closed:
        t = t[:-1]
    return np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], 1)


class ClosestPoints:
    """Closest points of a (resampled) polyline to query points.

    A KD-tree finds the nearest vertex; with ``segment=True`` the answer is refined to
    the closest point on the two polyline segments adjacent to that vertex (exact on the
    polyline whenever the nearest vertex is adjacent to the closest segment, which holds
    for vertices spaced well below the curvature radius).
    """

    def __init__(self, vertices: np.ndarray, *, closed: bool, segment: bool = True):
        from scipy.spatial import cKDTree

        self.v = np.asarray(vertices, float)
        self.closed = closed
        self.segment = segment
        self.tree = cKDTree(self.v)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """(K, 2) closest points (mm) for (K, 2) queries."""
        q = np.asarray(q, float)
        _, i = self.tree.query(q)
        if not self.segment or len(self.v) < 2:
            return self.v[i]
        n = len(self.v)
        best = self.v[i].copy()
        bestd = np.sum((q - best) ** 2, 1)
        for j0, j1 in ((i - 1, i), (i, i + 1)):
            if self.closed:
                j0, j1 = j0 % n, j1 % n
                ok = np.ones(len(q), bool)
            else:
                ok = (j0 >= 0) & (j1 < n)
                j0, j1 = np.clip(j0, 0, n - 1), np.clip(j1, 0, n - 1)
            a, b = self.v[j0], self.v[j1]
            ab = b - a
            L2 = np.maximum(np.sum(ab * ab, 1), 1e-300)
            t = np.clip(np.sum((q - a) * ab, 1) / L2, 0.0, 1.0)
            c = a + t[:, None] * ab
            d = np.sum((q - c) ** 2, 1)
            better = ok & (d < bestd)
            best[better], bestd[better] = c[better], d[better]
        return best


class PairedClosestPoints:
    """Closest points of stacked query contours, each searched on its own polyline only:
    ``parts`` lists ``(rows, ClosestPoints)``, ``rows`` the slice of the queries that
    belong to that polyline."""

    def __init__(self, parts: list[tuple[slice, ClosestPoints]]):
        self.parts = parts

    def __call__(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, float)
        out = np.empty_like(q)
        for rows, cp in self.parts:
            out[rows] = cp(q[rows])
        return out


def has_area(contour) -> bool:
    """A contour that can enclose a region: finite, with at least three distinct points."""
    p = np.asarray(contour, float).reshape(-1, 2)
    return bool(np.isfinite(p).all()) and len(np.unique(p, axis=0)) >= 3


def area_centroid(poly: np.ndarray) -> np.ndarray:
    """(2,) area centroid (mm) of a closed contour (its vertex mean when it has no area)."""
    p = np.asarray(poly, float).reshape(-1, 2)
    g = polygon(p) if has_area(p) else None
    if g is None or g.is_empty or g.area <= 0.0:
        return p.mean(axis=0)
    return np.array([g.centroid.x, g.centroid.y])


def pair_points(a: np.ndarray, b: np.ndarray) -> list[tuple[int, int]]:
    """One-to-one pairs ``(j, k)`` of points ``a[j]`` and ``b[k]`` (mm) with the least total
    distance (the assignment problem, solved exactly: Kuhn-Munkres, scipy's
    ``linear_sum_assignment``); the points left over on the longer side have no pair.
    Sorted by ``j``."""
    a, b = np.asarray(a, float).reshape(-1, 2), np.asarray(b, float).reshape(-1, 2)
    if not len(a) or not len(b):
        return []
    from scipy.optimize import linear_sum_assignment

    j, k = linear_sum_assignment(np.linalg.norm(a[:, None, :] - b[None], axis=2))
    return sorted(zip(j.tolist(), k.tolist()))


def pair_outlines(virtual: list[np.ndarray], real: list[np.ndarray]) -> list[tuple[int, int]]:
    """One-to-one pairs ``(j, k)`` of virtual outline ``j`` and real outline ``k``, both in the
    real frame (mm), with the least total distance between their area centroids
    (:func:`pair_points`).

    A model may hold a lesion that the mammogram does not show (outside the detector, or
    not outlined) and an image an outline the model has no lesion for; the outlines left
    over on either side have no pair, so that nothing is compared with the wrong lesion.
    With one outline on each side this is the single pair ``(0, 0)``.  Only outlines with
    an area (:func:`has_area`) are paired.
    """
    vi = [j for j, c in enumerate(virtual) if has_area(c)]
    ri = [k for k, c in enumerate(real) if has_area(c)]
    pairs = pair_points([area_centroid(virtual[j]) for j in vi], [area_centroid(real[k]) for k in ri])
    return [(vi[a], ri[b]) for a, b in pairs]


def polygon(poly: np.ndarray):
    """A valid shapely polygon of a contour (self-intersections repaired).

    An open breast contour is closed by the straight chest-wall chord between its ends.
    """
    import shapely
    from shapely.geometry import Polygon

    g = Polygon(np.asarray(poly, float))
    return g if g.is_valid else shapely.make_valid(g).buffer(0)
