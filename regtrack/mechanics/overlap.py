r"""Skin self-overlap: skin that went through other skin into the tissue.

Where the skin folds onto itself (the inframammary crease pressed shut by the lower plate,
tissue below the breast that the MRI segmentation kept, a bulge rolling over the skin
beside it) one patch of skin meets another.  The self-contact barrier (:mod:`.selfcontact`)
keeps a skin node out of every triangle outside its 2-ring, but not out of its own 2-ring's
patch (a crease sharper than the mesh), nor two edges from crossing; with the barrier off
(``[contact] self_contact_gap_mm = 0``) nothing in the energy stops a skin node from passing
through other skin into the tissue behind it.  This module measures how far that happened,
so that a result says so.

A boundary node ``i`` at ``x_i = X_i + u_i`` (mm) is *inside the tissue* when it lies in a
tetrahedron it is not a corner of (its barycentric coordinates there all ``>= -tol``, by
:class:`regtrack.tracking.locate.TetLocator`: in a conforming mesh a node lies in the
closure of its own tetrahedra only).  The candidates are the ``NEAREST_TETS`` tetrahedra
with the nearest centroids (a containing tetrahedron's centroid is within its own size of
the node).  Its *depth* ``d_i`` is its distance to the
nearest boundary triangle it is not a corner of: how far it went through the skin it
crossed, or less where its own skin next to it is nearer (a node enters the tissue through
a triangle it is not a corner of, so ``d_i`` grows continuously from 0 as it goes in).

Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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

    from regtrack.tracking.locate import BARY_TOL, TetLocator

    x = np.asarray(points, float) + np.asarray(u, float).reshape(-1, 3)
    T = np.asarray(tets, np.int64)[:, :4]
    faces = np.asarray(faces, np.int64)
    nodes = np.unique(faces)
    none = Overlaps(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
                    np.zeros((0, 3), np.int64), np.zeros((0, 3)))
    if len(nodes) == 0 or len(T) == 0:
        return none
    loc = TetLocator(x, T)
    k = min(len(T), NEAREST_TETS)
    _, near = loc.tree.query(x[nodes], k=k)
    near = near.reshape(len(nodes), k)
    lam = loc.bary(x[nodes], near)                                      # (n, k, 4)
    other = ~(T[near] == nodes[:, None, None]).any(axis=2) & ~loc.degenerate[near]
    over = nodes[((lam.min(axis=2) >= -BARY_TOL) & other).any(axis=1)]
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
