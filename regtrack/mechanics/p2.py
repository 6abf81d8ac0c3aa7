r"""Quadratic (10-node) tetrahedra: plain displacement P2 with the same neo-Hookean W.

Node order is meshio's / VTK's ``tetra10``: corners 0-3, then the mid-edge nodes of
edges (0,1), (1,2), (0,2), (0,3), (1,3), (2,3).  Shape functions in barycentric
coordinates :math:`L_i`: corners :math:`L_i(2L_i - 1)`, edges :math:`4 L_i L_j`.
Integration: the 4-point Gauss rule (degree 2, as CalculiX C3D10), isoparametric (curved
tets allowed).  Per quadrature point the stress and tangent are those of
:mod:`.tissue` with ``p = K (J - 1)``.  This is the peers' tet10 formulation
(peers/README.md), used for like-with-like comparisons; the skin membrane is not
available with P2.  Units: mm, N, MPa.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from regtrack.mechanics.tissue import _det3, force_entry, point_state, tangent_entry

EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
_A, _B = 0.5854101966249685, 0.1381966011250105
QUAD_L = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])  # barycentric
QUAD_W = np.full(4, 1.0 / 24.0)  # reference tet volume 1/6 split in 4


def shape_functions(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """N (Q, 10) and dN/dxi (Q, 10, 3) at barycentric points L (Q, 4), xi = (L1, L2, L3)."""
    Q = len(L)
    N = np.empty((Q, 10))
    dL = np.zeros((Q, 10, 4))  # derivatives wrt L0..L3
    for i in range(4):
        N[:, i] = L[:, i] * (2 * L[:, i] - 1)
        dL[:, i, i] = 4 * L[:, i] - 1
    for k, (i, j) in enumerate(EDGES):
        N[:, 4 + k] = 4 * L[:, i] * L[:, j]
        dL[:, 4 + k, i] = 4 * L[:, j]
        dL[:, 4 + k, j] = 4 * L[:, i]
    # L0 = 1 - xi1 - xi2 - xi3, Lk = xik
    dxi = dL[:, :, 1:] - dL[:, :, :1]
    return N, dxi


def reference_geometry(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradients ``G`` (E, Q, 10, 3) 1/mm, weights ``W`` (E, Q) mm^3 and ``N`` (Q, 10)."""
    N, dxi = shape_functions(QUAD_L)
    X = points[tets]  # (E, 10, 3)
    Jm = np.einsum("eai,qaj->eqij", X, dxi)  # dX/dxi (E, Q, 3, 3)
    det = np.linalg.det(Jm)
    inv = np.linalg.inv(Jm)
    G = np.einsum("qaj,eqji->eqai", dxi, inv)
    return G, det * QUAD_W[None, :], N


def p1_to_p2(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight-sided tet10 from tet4: ``(points, tets10, parent)``; ``parent`` (M, 2) are
    the corner nodes of each added mid-edge node (new nodes are appended)."""
    e = tets[:, EDGES].reshape(-1, 2)
    key = np.sort(e, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    mid = 0.5 * (points[uniq[:, 0]] + points[uniq[:, 1]])
    tets10 = np.concatenate([tets, len(points) + inv.reshape(-1, 6)], axis=1)
    return np.vstack([points, mid]), tets10, uniq


@njit(cache=True)
def tet10_kernel(x, tets, G, W, c1, kappa, want_k, f, data, base, rowstride):
    """P2 neo-Hookean: accumulate forces ``f`` and (optionally) the tangent into ``data``.

    Returns (energy N mm, number of quadrature points with J <= 0).
    """
    ne, nq, nn = G.shape[0], G.shape[1], G.shape[2]
    F = np.empty((3, 3))
    H = np.empty((3, 3))
    fa = np.empty((nn, 3))
    ha = np.empty((nn, 3))
    energy = 0.0
    bad = 0
    for e in range(ne):
        for q in range(nq):
            for i in range(3):
                for J_ in range(3):
                    s = 0.0
                    for a in range(nn):
                        s += x[tets[e, a], i] * G[e, q, a, J_]
                    F[i, J_] = s
            J = _det3(F)
            if J <= 0.0:
                bad += 1
                continue
            I1, Jm23, mu_e = point_state(F, J, c1[e], G[e, q], H, fa, ha)
            p = kappa[e] * (J - 1.0)
            w = W[e, q]
            energy += w * (c1[e] * (Jm23 * I1 - 3.0) + 0.5 * kappa[e] * (J - 1.0) ** 2)
            for a in range(nn):
                n = tets[e, a]
                for i in range(3):
                    f[n, i] += w * force_entry(fa, ha, a, i, mu_e, I1, p, J)
            if not want_k:
                continue
            cvol = (kappa[e] * J + p) * J
            cgeo = mu_e * I1 / 3.0 - p * J
            for a in range(nn):
                rs = rowstride[tets[e, a]]
                for b in range(nn):
                    gg = 0.0
                    for L in range(3):
                        gg += G[e, q, a, L] * G[e, q, b, L]
                    b0 = base[e, a, b]
                    for i in range(3):
                        for k in range(3):
                            data[b0 + i * rs + k] += w * tangent_entry(fa, ha, a, b, i, k, mu_e,
                                                                       I1, cvol, cgeo, gg)
    return energy, bad


def model_to_p2(model):
    """Straight-sided tet10 copy of a tet4 :class:`~regtrack.model.types.BreastModel`.

    Mid-edge nodes are appended after the original nodes (so displacements of the
    original nodes keep their indices); a mid-edge node is fixed when both its corners
    are; the skin keeps its corner triangles (P2 runs without the membrane).
    """
    from dataclasses import replace

    pts, t10, parent = p1_to_p2(model.points, model.tets)
    fixed = np.concatenate([model.fixed, model.fixed[parent[:, 0]] & model.fixed[parent[:, 1]]])
    return replace(model, points=pts, tets=t10, fixed=fixed,
                   meta={**model.meta, "p2_from_p1": True, "n_corner_nodes": len(model.points)})


def boundary_faces6(points: np.ndarray, tets10: np.ndarray) -> np.ndarray:
    """Outward 6-node boundary triangles (T, 6) of a tet10 mesh: corners c0, c1, c2, then
    the mid-edge nodes of (c0, c1), (c1, c2), (c2, c0)."""
    from regtrack.mechanics.meshes import boundary_faces

    tri = boundary_faces(points, tets10[:, :4])
    e = tets10[:, EDGES].reshape(-1, 2)
    mids = tets10[:, 4:].reshape(-1)
    key = np.sort(e, axis=1)
    uniq, first = np.unique(key, axis=0, return_index=True)
    n = len(points)
    codes = uniq[:, 0] * n + uniq[:, 1]

    def mid(a, b):
        k = np.minimum(a, b) * n + np.maximum(a, b)
        return mids[first[np.searchsorted(codes, k)]]

    return np.column_stack([tri, mid(tri[:, 0], tri[:, 1]), mid(tri[:, 1], tri[:, 2]), mid(tri[:, 2], tri[:, 0])])
