"""Point location in a tetrahedral mesh and barycentric interpolation.

A point ``q`` lies in tetrahedron ``e`` with nodes ``x_0 .. x_3`` when its barycentric
coordinates

.. math::

    (\\lambda_1, \\lambda_2, \\lambda_3)^T = T_e^{-1} (q - x_0), \\qquad
    T_e = [x_1 - x_0,\\; x_2 - x_0,\\; x_3 - x_0], \\qquad
    \\lambda_0 = 1 - \\lambda_1 - \\lambda_2 - \\lambda_3

are all ``>= -tol``.  Any nodal field ``u`` of the linear (P1) mesh is then
``u(q) = sum_k lambda_k u(x_k)``; in particular a material point keeps its element and
barycentric coordinates through a deformation, so its deformed position is
``sum_k lambda_k x_k'`` with the deformed node positions ``x'``: the exact image of
``q`` under the piecewise-linear finite-element deformation.

Search: candidate tetrahedra are the ``k`` nearest element centroids (scipy
``cKDTree``), tested all at once (vectorised); points not found are retried with a
larger ``k``, so the result does not depend on a lucky ``k``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

#: Barycentric tolerance: a point this far outside a tet (relative) still counts as inside,
#: so points on shared faces and on the boundary are found.
BARY_TOL = 1e-9


@dataclass
class Location:
    """Where points lie in a tet mesh.

    Attributes
    ----------
    element : (M,) int
        Containing tetrahedron, -1 for points outside the mesh.
    bary : (M, 4) float
        Barycentric coordinates in that tetrahedron (NaN where outside).
    """

    element: np.ndarray
    bary: np.ndarray

    @property
    def inside(self) -> np.ndarray:
        """(M,) bool: the point lies in the mesh."""
        return self.element >= 0

    def subset(self, mask) -> Location:
        return Location(self.element[mask], self.bary[mask])

    def interpolate(self, tets: np.ndarray, values: np.ndarray) -> np.ndarray:
        """P1 interpolation ``sum_k lambda_k values[tets[e, k]]`` (NaN where outside).

        Parameters
        ----------
        tets : (E, 4) int
        values : (N, ...) float
            Nodal values (e.g. deformed positions, mm).
        """
        values = np.asarray(values, float)
        out = np.full((len(self.element),) + values.shape[1:], np.nan)
        ok = self.inside
        if ok.any():
            nodes = np.asarray(tets)[self.element[ok]]                  # (m, 4)
            out[ok] = np.einsum("mk,mk...->m...", self.bary[ok], values[nodes])
        return out


class TetLocator:
    """Locate points in the tetrahedral mesh ``(points, tets)`` (mm).

    Parameters
    ----------
    points : (N, 3) float
        Node positions (mm); reference or deformed.
    tets : (E, 4) int
        Linear tetrahedra.
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray):
        self.points = np.asarray(points, float)
        self.tets = np.asarray(tets, np.int64)
        x = self.points[self.tets]                                     # (E, 4, 3)
        self.x0 = x[:, 0]
        T = np.transpose(x[:, 1:] - x[:, :1], (0, 2, 1))               # columns x_k - x_0
        det = np.linalg.det(T)
        scale = np.maximum(np.abs(T).max(axis=(1, 2)), 1e-300) ** 3
        self.degenerate = np.abs(det) <= 1e-12 * scale
        if self.degenerate.any():
            log.warning("%d degenerate tetrahedra are skipped by point location",
                        int(self.degenerate.sum()))
        T[self.degenerate] = np.eye(3)
        self.Tinv = np.linalg.inv(T)
        self.centroids = x.mean(axis=1)
        self.tree = cKDTree(self.centroids)
        #: largest centroid-to-node distance (mm): a tet containing q has its centroid
        #: within this radius of q
        r = np.linalg.norm(x - self.centroids[:, None], axis=-1)
        self.r_max = float(r.max()) * (1 + 1e-9)
        self.node_tree: cKDTree | None = None

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def bary(self, q: np.ndarray, elements: np.ndarray) -> np.ndarray:
        """(M, K, 4) barycentric coordinates of (M, 3) points in (M, K) candidate tets."""
        d = q[:, None, :] - self.x0[elements]                          # (M, K, 3)
        lam = np.einsum("mkij,mkj->mki", self.Tinv[elements], d)
        return np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)

    def locate(self, q, *, k: int = 12, tol: float = BARY_TOL) -> Location:
        """Containing tetrahedron and barycentric coordinates of (M, 3) points ``q`` (mm).

        Points with no containing tetrahedron get element -1 (see :attr:`Location.inside`).
        Among several containing tets (shared faces) the one with the largest minimum
        barycentric coordinate is taken.  First the ``k`` nearest centroids are tested;
        points not found there are tested against *every* tet whose centroid lies within
        ``R_max`` (the largest centroid-to-node distance of the mesh), a complete
        candidate set, so the answer never depends on ``k``.
        """
        q = np.atleast_2d(np.asarray(q, float))
        M = len(q)
        element = np.full(M, -1, np.int64)
        bary = np.full((M, 4), np.nan)
        kk = min(k, self.n_tets)
        _, cand = self.tree.query(q, k=kk)
        cand = np.asarray(cand).reshape(M, kk)
        self._test(q, np.arange(M), cand, element, bary, tol)
        todo = np.flatnonzero(element < 0)
        if len(todo):
            lists = self.tree.query_ball_point(q[todo], r=self.r_max)
            for chunk in np.array_split(np.arange(len(todo)), max(1, len(todo) // 256)):
                width = max((len(lists[i]) for i in chunk), default=0)
                if width == 0:
                    continue
                pad = np.full((len(chunk), width), -1, np.int64)
                for row, i in enumerate(chunk):
                    pad[row, :len(lists[i])] = lists[i]
                self._test(q, todo[chunk], pad, element, bary, tol)
        return Location(element, bary)

    def _test(self, q: np.ndarray, idx: np.ndarray, cand: np.ndarray, element: np.ndarray,
              bary: np.ndarray, tol: float) -> None:
        """Test points ``q[idx]`` against candidate tets ``cand`` (-1 = padding), in place."""
        valid = cand >= 0
        c = np.where(valid, cand, 0)
        lam = self.bary(q[idx], c)                                     # (m, K, 4)
        score = lam.min(-1)
        score[~valid | self.degenerate[c]] = -np.inf
        best = np.argmax(score, axis=1)
        rows = np.arange(len(idx))
        found = score[rows, best] >= -tol
        element[idx[found]] = c[found, best[found]]
        bary[idx[found]] = lam[found, best[found]]

    def snap(self, q, *, k: int = 24) -> tuple[Location, np.ndarray]:
        """Nearest mesh point of each (M, 3) point (for points just outside the mesh).

        Among the ``k`` tets with the nearest centroids, the barycentric coordinates are
        clipped to ``>= 0`` and renormalised (a point of the tet); the closest such point
        is kept.  Returns its location and the distance (mm) to it (an upper bound of the
        distance to the mesh; 0 for points inside).
        """
        q = np.atleast_2d(np.asarray(q, float))
        kk = min(k, self.n_tets)
        _, cand = self.tree.query(q, k=kk)
        cand = np.asarray(cand).reshape(len(q), kk)
        lam = np.clip(self.bary(q, cand), 0.0, None)
        lam /= lam.sum(-1, keepdims=True)
        pts = np.einsum("mkj,mkjd->mkd", lam, self.points[self.tets[cand]])
        dist = np.linalg.norm(pts - q[:, None], axis=-1)
        dist[self.degenerate[cand]] = np.inf
        best = np.argmin(dist, axis=1)
        rows = np.arange(len(q))
        return Location(cand[rows, best], lam[rows, best]), dist[rows, best]

    def distance_to_nodes(self, q) -> np.ndarray:
        """(M,) distance (mm) from each point to the nearest mesh node."""
        if self.node_tree is None:
            self.node_tree = cKDTree(self.points)
        return self.node_tree.query(np.atleast_2d(np.asarray(q, float)))[0]


def transfer(location: Location, tets: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Positions (mm) of located material points in another configuration of the mesh.

    ``positions`` (N, 3) are the node positions of that configuration (e.g. the
    compressed MLO state); the result is ``sum_k lambda_k positions[tets[e, k]]``.
    """
    return location.interpolate(tets, positions)
