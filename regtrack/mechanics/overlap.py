r"""Skin self-overlap: skin that went through other skin into the tissue.

Where the skin folds onto itself (the inframammary crease pressed shut by the lower plate,
tissue below the breast that the MRI segmentation kept, a bulge rolling over the skin
beside it) one patch of skin meets another.  The model has no self-contact: nothing in its
energy stops a skin node from passing through the other patch into the tissue behind it.
This module measures how far that happened, so that a result says so.

A boundary node ``i`` at ``x_i = X_i + u_i`` (mm) is *inside the tissue* when it lies in a
tetrahedron it is not a corner of (barycentric coordinates all above ``-BARY_TOL``: in a
conforming mesh a node lies in the closure of its own tetrahedra only).  The candidates
are the ``NEAREST_TETS`` tetrahedra with the nearest centroids (a containing tetrahedron's
centroid is within its own size of the node).  Its *depth* ``d_i`` is its distance to the
nearest boundary triangle it is not a corner of: how far it went through the skin it
crossed, or less where its own skin next to it is nearer (a node enters the tissue through
a triangle it is not a corner of, so ``d_i`` grows continuously from 0 as it goes in).

Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

#: barycentric margin (-): a node on a face of another tetrahedron is in it (in a conforming
#: mesh a node lies in the closure of its own tetrahedra only)
BARY_TOL = 1e-9
#: a node in the tissue at most this far (mm) from the skin it meets touches it
DEPTH_TOL_MM = 1e-9
#: tetrahedra searched per node: those with the nearest centroids
NEAREST_TETS = 48
#: boundary triangles searched per overlapping node for the skin it crossed
NEAREST_FACES = 32


def closest_on_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                        c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The closest points ``q`` (K, 3) of triangles ``(a, b, c)`` (K, 3 each) to points ``p``
    (K, 3), and their barycentric weights ``w`` (K, 3), ``q = w_a a + w_b b + w_c c``: by
    the triangle's Voronoi regions (Ericson, *Real-Time Collision Detection*, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        w = np.stack([1.0 - (vb + vc) / den, vb / den, vc / den], axis=1)  # interior
        t_ab, t_ac = d1 / (d1 - d3), d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    one = np.ones_like(d1)
    zero = np.zeros_like(d1)
    # the edges, then the corners (Ericson's tests; a later region wins)
    regions = [((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), (zero, 1.0 - t_bc, t_bc)),
               ((vb <= 0) & (d2 >= 0) & (d6 <= 0), (1.0 - t_ac, zero, t_ac)),
               ((vc <= 0) & (d1 >= 0) & (d3 <= 0), (1.0 - t_ab, t_ab, zero)),
               ((d6 >= 0) & (d5 <= d6), (zero, zero, one)),
               ((d3 >= 0) & (d4 <= d3), (zero, one, zero)),
               ((d1 <= 0) & (d2 <= 0), (one, zero, zero))]
    for mask, wk in regions:
        w = np.where(mask[:, None], np.stack(wk, axis=1), w)
    q = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    return q, w


@njit(cache=True)
def _inside_other(x, T, nodes, near, tol):
    """(len(nodes),) bool: node ``nodes[i]`` lies in one of the tetrahedra ``near[i]`` it
    is not a corner of (barycentric coordinates all >= ``-tol``)."""
    out = np.zeros(nodes.shape[0], np.bool_)
    for i in range(nodes.shape[0]):
        n = nodes[i]
        for m in range(near.shape[1]):
            e = near[i, m]
            if T[e, 0] == n or T[e, 1] == n or T[e, 2] == n or T[e, 3] == n:
                continue
            a = T[e, 0]
            # columns: the edges from corner 0; Cramer's rule for D lam = x_n - x_a
            d00 = x[T[e, 1], 0] - x[a, 0]; d01 = x[T[e, 2], 0] - x[a, 0]; d02 = x[T[e, 3], 0] - x[a, 0]
            d10 = x[T[e, 1], 1] - x[a, 1]; d11 = x[T[e, 2], 1] - x[a, 1]; d12 = x[T[e, 3], 1] - x[a, 1]
            d20 = x[T[e, 1], 2] - x[a, 2]; d21 = x[T[e, 2], 2] - x[a, 2]; d22 = x[T[e, 3], 2] - x[a, 2]
            r0 = x[n, 0] - x[a, 0]; r1 = x[n, 1] - x[a, 1]; r2 = x[n, 2] - x[a, 2]
            det = (d00 * (d11 * d22 - d12 * d21) - d01 * (d10 * d22 - d12 * d20)
                   + d02 * (d10 * d21 - d11 * d20))
            if det == 0.0:
                continue
            l0 = (r0 * (d11 * d22 - d12 * d21) - d01 * (r1 * d22 - d12 * r2)
                  + d02 * (r1 * d21 - d11 * r2)) / det
            l1 = (d00 * (r1 * d22 - d12 * r2) - r0 * (d10 * d22 - d12 * d20)
                  + d02 * (d10 * r2 - r1 * d20)) / det
            l2 = (d00 * (d11 * r2 - r1 * d21) - d01 * (d10 * r2 - r1 * d20)
                  + r0 * (d10 * d21 - d11 * d20)) / det
            if l0 >= -tol and l1 >= -tol and l2 >= -tol and l0 + l1 + l2 <= 1.0 + tol:
                out[i] = True
                break
    return out


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance (K,) mm from points ``p`` (K, 3) to triangles ``(a, b, c)``."""
    return np.linalg.norm(p - closest_on_triangle(p, a, b, c)[0], axis=1)


@dataclass
class Overlaps:
    """The skin nodes inside the tissue at one state: ``nodes`` (K,), their depths ``d``
    (K,) mm, closest points ``q`` (K, 3), the crossed triangles ``tri`` (K, 3) and the
    weights ``w`` (K, 3) of ``q`` on them."""

    nodes: np.ndarray
    d: np.ndarray
    q: np.ndarray
    tri: np.ndarray
    w: np.ndarray

    @property
    def depth(self) -> float:
        return float(self.d.max()) if len(self.d) else 0.0


def overlaps(points: np.ndarray, tets: np.ndarray, faces: np.ndarray, u: np.ndarray) -> Overlaps:
    """The boundary nodes of ``faces`` (F, 3) inside the tissue of ``tets`` (E, 4+) at
    ``x = points + u`` (N, 3 each, mm)."""
    from scipy.spatial import cKDTree

    x = np.asarray(points, float) + np.asarray(u, float).reshape(-1, 3)
    T = np.ascontiguousarray(np.asarray(tets)[:, :4], np.int64)
    faces = np.ascontiguousarray(faces, np.int64)
    nodes = np.unique(faces)
    none = Overlaps(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
                    np.zeros((0, 3), np.int64), np.zeros((0, 3)))
    if len(nodes) == 0 or len(T) == 0:
        return none
    k = min(len(T), NEAREST_TETS)
    _, near = cKDTree(x[T].mean(axis=1)).query(x[nodes], k=k)
    over = nodes[_inside_other(x, T, nodes, near.reshape(len(nodes), k), BARY_TOL)]
    if len(over) == 0:
        return none
    # the skin it crossed: the nearest boundary triangle it is not a corner of
    kf = min(len(faces), NEAREST_FACES)
    _, nf = cKDTree(x[faces].mean(axis=1)).query(x[over], k=kf)
    tri = faces[nf.reshape(len(over), kf)]                              # (n, kf, 3)
    own = (tri == over[:, None, None]).any(axis=2)
    P = np.repeat(x[over], kf, axis=0)
    q, w = closest_on_triangle(P, *(x[tri[..., m]].reshape(-1, 3) for m in range(3)))
    d = np.where(own, np.inf, np.linalg.norm(P - q, axis=1).reshape(len(over), kf))
    best = np.argmin(d, axis=1)
    row = np.arange(len(over))
    dd = d[row, best]
    sel = np.isfinite(dd) & (dd > DEPTH_TOL_MM)
    flat = row * kf + best
    return Overlaps(over[sel], dd[sel], q[flat][sel], tri[row, best][sel], w[flat][sel])


def skin_overlap(points: np.ndarray, tets: np.ndarray, u: np.ndarray,
                 faces: np.ndarray) -> tuple[float, int]:
    """``(depth_mm, nodes)``: the deepest overlap (0 when none) and the number of boundary
    nodes ``faces`` (F, 3) inside the tissue of ``tets`` at ``x = points + u`` (mm)."""
    o = overlaps(points, tets, faces, u)
    return o.depth, len(o.nodes)
