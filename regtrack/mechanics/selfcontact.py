r"""The outer surface against itself: a barrier that keeps the skin out of the tissue.

Where the skin folds onto itself (the inframammary crease pressed shut by a plate, the
breast's underside resting on tissue below it that the MRI segmentation kept, a bulge
rolling over the skin beside it) one patch of the model's outer surface meets another.
This term of the incremental potential (:mod:`.minimise`) stops one passing through the
other.

Every boundary node ``i`` (position ``x_i``, tributary reference area ``A_i`` in mm^2) and
every boundary triangle ``T`` outside its 2-ring (no corner of ``T`` is ``i`` or a surface
neighbour of ``i``), at the distance ``d = dist(x_i, T)`` (mm), add the log barrier of
*Incremental Potential Contact* (Li et al., SIGGRAPH 2020, eq. 6) when ``d < dhat``:

.. math::

    \Pi_S = \sum_{(i, T):\, d < \hat d} \kappa A_i\, b(d), \qquad
    b(d) = -(d - \hat d)^2 \ln(d / \hat d) \quad\text{(mm}^2\text{; } \Pi_S \text{ in N mm)},

with ``kappa`` (MPa/mm) the plates' normal penalty (:func:`.contact.automatic_penalty`) and
``dhat`` (mm) the barrier's reach (``[contact] self_contact_gap_mm``).  ``b`` is C2 at
``dhat`` (it and its first two derivatives vanish there) and grows without bound as ``d ->
0``, so a state of finite potential has no node on a triangle it faces.  The line search
never lets a node cross a triangle within a step (:meth:`SkinBarrier.near`, below), so no
boundary node can enter the tissue: the skin may touch itself, pressing with ``-kappa
b'(d)`` (MPa), but not go through.

Derivatives (envelope theorem; ``q = sum_k w_k v_k`` the closest point of ``T`` with its
barycentric weights, ``n = (x_i - q) / d``): ``g = dd/dy`` is ``n`` for ``x_i`` and ``-w_k
n`` for ``v_k`` (``y`` the pair's 12 coordinates): exact in every Voronoi region of the
triangle.  The Hessian of a pair's term, ``kappa A_i (b''(d) g g^T + b'(d) d^2d/dy^2)``, is
projected onto the positive semi-definite cone (its 12 eigenvalues clamped at zero; IPC,
section 4.3).  Its second part matters: the distance is concave along a triangle turning
under a node, and without that curvature Newton's steps overshoot a fold's equilibrium and
alternate across it, each only a few percent shorter than the last.  ``d^2d/dy^2``
(:func:`distance_hessian`) follows from ``f = |r|^2 / 2``, ``r = x_i - v_a - E t``: the
closest point in the region's own parameters ``t`` (a face: the weights of ``v_1``,
``v_2``; an edge: that of its second end; a corner: none) with ``E`` the edges from
``v_a``, and the minimum over ``t`` differentiated twice (implicit function theorem):

.. math::

    \nabla^2 f = A^T A - G^T (E^T E)^{-1} G, \qquad
    \nabla^2 d = (\nabla^2 f - g g^T) / d,

``A = dr/dy = [I, -w_0 I, -w_1 I, -w_2 I]`` and row ``j`` of ``G`` the derivative of
``e_j . r`` (``e_j^T A``, plus ``r`` at ``v_j`` and ``-r`` at ``v_a``).

Steps that cannot cross (additive continuous collision detection; Li et al., *Codimensional
IPC*, 2021): moving the nodes by ``alpha Delta``, with ``c`` the mean motion of the pair's
four nodes or zero (the smaller bound is used),

.. math::

    |d(\alpha) - d(0)| \le \alpha\, m, \qquad m = |\Delta_i - c| + \max_k |\Delta_{v_k} - c|,

because the distance is invariant under a common translation, 1-Lipschitz in the point, and
a triangle whose corners move by at most ``r`` moves each of its points by at most ``r``.
So ``alpha <= s d(0) / m`` (``s = 0.9``) keeps the pair apart, and a pair with ``d(0) >=
dhat + m`` stays beyond the barrier's reach for every ``alpha`` in ``[0, 1]``: the pairs of a
line search are found once, before its trials.  Repeating the bound from the distance
reached (additive CCD) gives each pair's time of impact, when its distance first falls to
``(1 - s) d(0)``; a pair sliding along the other surface keeps its distance and may take the
whole step.  The line search starts from the smallest time of impact.

Which pairs to test (a neighbour list with a skin, as in molecular dynamics; Verlet 1967):
the list holds every pair closer than ``S = PATTERN_MARGIN dhat + LIST_SKIN_MM`` at the
state ``x_b`` where it was made.  Moving the surface's nodes by ``w`` (less a common
translation, which changes no distance) changes a pair's distance by at most ``2 max|w|``
(the 1-Lipschitz bound above), so a pair not on the list stays farther than ``S - 2
max|w|``: while that is at least the distance asked about, the list holds every pair that
matters, and the tree search is skipped.  A step that moves the surface further is searched
afresh.  The pairs come out in the order (node, triangle) whichever way they were found.

The barrier acts between nodes and triangles; two edges may still cross with every node
outside (a fold meeting another at a sharp crease), which this term does not see.  A node
and the triangles of its 2-ring are left out: they are the same patch of skin, which the
tetrahedra below it keep apart; wrinkled by a plate, the patch would otherwise press on
itself at the barrier's reach and stiffen the skin against a fold that the mesh is too
coarse to resolve.

Units: mm, N, MPa; energies in N mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from regtrack.mechanics.overlap import closest_on_triangle

#: Fraction of the distance a step may close (the conservative CCD's safety factor).
CCD_SAFETY = 0.9
#: Strides of the additive CCD per pair before its time reached is kept as its bound.
ACCD_ITERATIONS = 64
#: Pairs within this many reaches enter the system matrix's pattern (with zero blocks).
PATTERN_MARGIN = 2.0
#: Candidate pairs per surface node a step's search may test; a longer step (its nodes
#: moving far past their neighbours) is bounded to the part that fits (halved until it does).
BROAD_PHASE_BUDGET = 128
#: The neighbour list's skin (mm): the list serves every state whose surface has moved by
#: less than half this (besides a common translation) since it was made (module docstring).
LIST_SKIN_MM = 2.0


def barrier(d: np.ndarray, dhat: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``b(d)``, ``b'(d)`` and ``b''(d)`` (mm^2, mm, 1) of the log barrier for ``0 < d``,
    zero from ``dhat`` on (module docstring)."""
    d = np.asarray(d, float)
    inside = d < dhat
    with np.errstate(divide="ignore", invalid="ignore"):
        g = d - dhat
        L = np.log(d / dhat)
        b = np.where(inside, -g * g * L, 0.0)
        b1 = np.where(inside, -2.0 * g * L - g * g / d, 0.0)
        b2 = np.where(inside, -2.0 * L - 4.0 * g / d + g * g / (d * d), 0.0)
    return b, b1, b2


def distance_hessian(r: np.ndarray, w: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """``d^2 d / dy^2`` (P, 12, 12), 1/mm, of the distances ``d = |r|`` between points and
    triangles (module docstring): ``r`` (P, 3) from the closest point to the point, ``w``
    (P, 3) its barycentric weights (zero off the Voronoi region's corners), ``corners``
    (P, 3, 3) the triangles; ``y`` = (point, corner 0, corner 1, corner 2) coordinates."""
    P = len(r)
    d = np.linalg.norm(r, axis=1)
    c = np.concatenate([np.ones((P, 1)), -w], axis=1)                      # A = c (x) I
    eye = np.eye(3)
    AtA = (c[:, :, None, None, None] * c[:, None, None, :, None] * eye[None, None, :, None, :])
    H = AtA.reshape(P, 12, 12)
    # the region's free parameters: the active corners after the first one
    active = w > 0.0
    a = np.argmax(active, axis=1)                                          # v_a
    G = np.zeros((P, 2, 12))
    E = np.zeros((P, 2, 3))
    mask = np.zeros((P, 2), bool)
    slot = np.zeros(P, np.int64)
    for j in range(3):
        use = np.flatnonzero(active[:, j] & (j != a))
        k = slot[use]
        e = corners[use, j] - corners[use, a[use]]
        E[use, k] = e
        mask[use, k] = True
        g = c[use, :, None] * e[:, None, :]                                # e_j^T A, (n, 4, 3)
        g[:, 1 + j] += r[use]
        g[np.arange(len(use)), 1 + a[use]] -= r[use]
        G[use, k] = g.reshape(-1, 12)
        slot[use] += 1
    EtE = E @ np.swapaxes(E, 1, 2) + (~mask)[:, :, None] * np.eye(2)       # 1 for an unused slot
    # pinv: a triangle crushed to a segment has a singular E^T E (no curvature term there)
    H -= np.swapaxes(G, 1, 2) @ np.linalg.pinv(EtE, rcond=1e-10, hermitian=True) @ G
    grad = (c[:, :, None] * (r / d[:, None])[:, None, :]).reshape(P, 12)
    return (H - grad[:, :, None] * grad[:, None, :]) / d[:, None, None]


def _psd(H: np.ndarray) -> np.ndarray:
    """The symmetric matrices ``H`` (P, n, n) with their negative eigenvalues clamped to zero."""
    lam, V = np.linalg.eigh(0.5 * (H + np.swapaxes(H, 1, 2)))
    return (V * np.maximum(lam, 0.0)[:, None, :]) @ np.swapaxes(V, 1, 2)


def _midrange(v: np.ndarray) -> np.ndarray:
    """The middle (3,) of the bounding box of the vectors ``v`` (K, 3): the common
    translation whose removal leaves the smallest largest vector."""
    if len(v) == 0:
        return np.zeros(3)
    return 0.5 * (v.max(axis=0) + v.min(axis=0))


def _spheres(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres of triangles ``corners`` (F, 3, 3): centres (F, 3), radii (F,) mm."""
    centre = corners.mean(axis=1)
    return centre, np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1)


def _ordered(node: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs sorted by node, then triangle: one order however they were found."""
    order = np.lexsort((tri, node))
    return node[order], tri[order]


@dataclass
class Pairs:
    """Node-triangle pairs: boundary nodes ``node`` (P,) and triangles ``tri`` (P,) (rows
    of :attr:`SkinBarrier.faces`)."""

    node: np.ndarray
    tri: np.ndarray

    def __len__(self) -> int:
        return len(self.node)


@dataclass
class BarrierEval:
    """The barrier at one state: ``energy`` (N mm), ``grad`` (3N,) N, the projected
    Hessian as ``(rows, cols, vals)`` dof triplets (N/mm; None unless asked), the number of
    pairs within reach and the smallest distance (mm; inf without pairs)."""

    energy: float
    grad: np.ndarray
    hess: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    n_active: int
    d_min: float


class SkinBarrier:
    """The self-contact barrier of a mesh's outer surface (module docstring).

    Parameters
    ----------
    points : (N, 3) reference coordinates (mm).
    faces : (F, 3) the outer triangles (node indices).
    areas : (N,) tributary reference area of each node on the outer surface (mm^2).
    kappa : barrier stiffness (MPa/mm).
    dhat : the barrier's reach (mm), below the smallest distance between a node and a
        triangle outside its 2-ring in the reference configuration (else the reference is
        not stress free; :meth:`check_reference`).
    """

    def __init__(self, points: np.ndarray, faces: np.ndarray, areas: np.ndarray, *,
                 kappa: float, dhat: float) -> None:
        self.X = np.asarray(points, float)
        self.faces = np.asarray(faces, np.int64)
        self.nodes = np.unique(self.faces)
        self.areas = np.asarray(areas, float)
        self.kappa = float(kappa)
        self.dhat = float(dhat)
        self.n_dofs = 3 * len(self.X)
        # the surface's edges (both ways) and its nodes, as sorted keys i * N + j
        E = self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        n = len(self.X)
        self._adjacent = np.unique(np.concatenate([E[:, 0] * n + E[:, 1], E[:, 1] * n + E[:, 0],
                                                   self.nodes * n + self.nodes]))
        # the neighbour list: surface positions where made, its pairs, its radius (mm)
        self._list: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None

    def _neighbours(self, node: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """Whether a triangle (``corners`` (P, 3)) has ``node`` (P,) or one of the node's
        surface neighbours as a corner: a triangle of the node's 2-ring."""
        keys = node[:, None] * len(self.X) + corners
        return np.isin(keys, self._adjacent).any(axis=1)

    # -- pairs --------------------------------------------------------------------------
    def near(self, u: np.ndarray, du: np.ndarray | None = None, *,
             margin: float = 1.0) -> tuple[Pairs, float]:
        """The pairs that can come within reach while the nodes move from ``x = X + u`` by
        ``alpha du`` for ``alpha`` in ``[0, a]`` (``du`` None: those within ``margin``
        times the reach at ``x``), and ``a``: the largest step ``<= 1`` that no pair can
        cross (additive CCD, :meth:`_time_of_impact`; 1 without motion; at most ``2^-k``
        when the search of the whole step exceeds ``BROAD_PHASE_BUDGET`` and its ``2^-k``
        part does not).  Both (N, 3) mm.  The pairs are those of the neighbour list while
        it serves (module docstring), else of a tree search."""
        x = self.X + np.asarray(u, float).reshape(-1, 3)
        F = self.faces
        D = np.zeros_like(x) if du is None else np.asarray(du, float).reshape(-1, 3)
        if du is not None:  # pairs meet by their relative motion: take out a common one
            D = D - _midrange(D[self.nodes])
        move = np.linalg.norm(D, axis=1)
        scale = 1.0
        listed = self._listed(x, move, margin * self.dhat)
        if listed is not None:
            node, tri = listed
        else:
            node, tri, D, scale = self._search(x, D, margin)
            move = np.linalg.norm(D, axis=1)
        d, _, _ = self._distance(x, node, tri)
        if du is None:
            sel = d < margin * self.dhat
            return Pairs(node[sel], tri[sel]), 1.0
        quad = np.concatenate([node[:, None], F[tri]], axis=1)           # (P, 4)
        Dq = D[quad]
        rel = np.linalg.norm(Dq - Dq.mean(axis=1, keepdims=True), axis=2)
        m = np.minimum(rel[:, 0] + rel[:, 1:].max(axis=1), move[node] + move[F[tri]].max(axis=1))
        sel = d < self.dhat + m
        toi = self._time_of_impact(x, D, node, tri, d, m)
        alpha = float(min(scale, scale * toi.min(initial=np.inf)))
        return Pairs(node[sel], tri[sel]), alpha

    def _listed(self, x: np.ndarray, move: np.ndarray, need: float
                ) -> tuple[np.ndarray, np.ndarray] | None:
        """The neighbour list's pairs when it holds every pair that comes closer than
        ``need`` (mm) while the nodes move from ``x`` by up to ``move`` (N,) mm (relative
        to a common translation); the list is made afresh at ``x`` when the old one does
        not serve and a fresh one would; None when the move is too long for any list."""
        s = self.nodes
        if self._list is not None:
            xb, node, tri, radius = self._list
            w = x[s] - xb
            w = w - _midrange(w)
            if radius - 2.0 * float((np.linalg.norm(w, axis=1) + move[s]).max()) >= need:
                return node, tri
        radius = PATTERN_MARGIN * self.dhat + LIST_SKIN_MM
        if radius - 2.0 * float(move[s].max(initial=0.0)) < need:
            return None
        node, tri, _, _ = self._search(x, np.zeros_like(x), radius / self.dhat)
        keep = self._distance(x, node, tri)[0] < radius
        self._list = (x[s].copy(), node[keep], tri[keep], radius)
        return node[keep], tri[keep]

    def _search(self, x: np.ndarray, D: np.ndarray, margin: float):
        """Tree search of the pairs that can come within ``margin`` reaches while the nodes
        move from ``x`` by ``alpha D``: ``(node, tri, D, scale)``, with ``D`` halved (and
        ``scale`` with it) until the search fits ``BROAD_PHASE_BUDGET``."""
        F = self.faces
        centre, radius = _spheres(x[F])
        scale = 1.0
        budget = BROAD_PHASE_BUDGET * len(self.nodes)
        while True:  # a step too long to search within the budget is searched for its part
            move = np.linalg.norm(D, axis=1)
            found = self._broad_phase(x[self.nodes], margin * self.dhat + move[self.nodes], centre,
                                      radius + move[F].max(axis=1),
                                      budget if move.any() else None)
            if found is not None:
                break
            D, scale = 0.5 * D, 0.5 * scale
        node, tri = _ordered(*self._beyond_ring(self.nodes[found[0]], found[1]))
        return node, tri, D, scale

    def _beyond_ring(self, node: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pairs whose triangle lies outside the node's 2-ring."""
        keep = ~self._neighbours(node, self.faces[tri])
        return node[keep], tri[keep]

    def _time_of_impact(self, x: np.ndarray, D: np.ndarray, node: np.ndarray, tri: np.ndarray,
                        d0: np.ndarray, m: np.ndarray) -> np.ndarray:
        """Additive CCD (Li et al. 2021, algorithm 1) of each pair moving from ``x`` by
        ``t D``: the pair advances by ``s d(t) / m`` (``s = CCD_SAFETY``; its distance stays
        above ``(1 - s) d(t)`` meanwhile, module docstring) until its distance falls below
        ``(1 - s) d0``; the time reached before that is its time of impact (inf: not before
        ``t = 1``).  A pair sliding along the other surface keeps its distance and advances
        in long strides; after ``ACCD_ITERATIONS`` the time reached is kept (a lower bound:
        safe)."""
        toi = np.full(len(node), np.inf)
        idx = np.flatnonzero(m > CCD_SAFETY * d0)    # the others cannot close to (1 - s) d0
        t = np.zeros(len(idx))
        d = d0[idx]
        for _ in range(ACCD_ITERATIONS):
            t_new = t + CCD_SAFETY * d / m[idx]
            go = t_new <= 1.0
            idx, t, t_new = idx[go], t[go], t_new[go]
            if len(idx) == 0:
                return toi
            d = np.linalg.norm(self._gap(x, D, t_new, node[idx], tri[idx]), axis=1)
            hit = d < (1.0 - CCD_SAFETY) * d0[idx]
            toi[idx[hit]] = t[hit]
            idx, t, d = idx[~hit], t_new[~hit], d[~hit]
        toi[idx] = t
        return toi

    def _gap(self, x: np.ndarray, D: np.ndarray, t: np.ndarray, node: np.ndarray,
             tri: np.ndarray) -> np.ndarray:
        """``x_i - q`` (P, 3) mm of the pairs at positions ``x + t D`` (``t`` per pair)."""
        c = x[self.faces[tri]] + t[:, None, None] * D[self.faces[tri]]
        p = x[node] + t[:, None] * D[node]
        q, _ = closest_on_triangle(p, c[:, 0], c[:, 1], c[:, 2])
        return p - q

    @staticmethod
    def _broad_phase(pts: np.ndarray, reach: np.ndarray, centre: np.ndarray, sweep: np.ndarray,
                     budget: int | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The (point, triangle) index pairs whose spheres meet: point ``k`` with radius
        ``reach[k]``, triangle ``j`` with centre ``centre[j]`` and radius ``sweep[j]`` (its
        bounding sphere grown by its corners' largest motion); None when the search would
        test more than ``budget`` pairs.  The triangles are queried in classes of radius
        within a factor 2, so that a few fast ones do not widen the search of all."""
        cls = np.ceil(np.log2(np.maximum(sweep, 0.5) / 0.5)).astype(np.int64)
        queries = []
        for k in np.unique(cls):
            ts = np.flatnonzero(cls == k)
            queries.append((ts, cKDTree(centre[ts]), reach + float(sweep[ts].max())))
        if budget is not None and sum(int(tree.query_ball_point(pts, r=r, return_length=True).sum())
                                      for _, tree, r in queries) > budget:
            return None
        out_p, out_t = [], []
        for ts, tree, r in queries:
            lists = tree.query_ball_point(pts, r=r, return_sorted=False)
            counts = np.fromiter((len(v) for v in lists), np.int64, len(lists))
            p = np.repeat(np.arange(len(pts)), counts)
            t = ts[np.concatenate([np.asarray(v, np.int64) for v in lists])]
            keep = np.linalg.norm(pts[p] - centre[t], axis=1) <= reach[p] + sweep[t]
            out_p.append(p[keep])
            out_t.append(t[keep])
        return np.concatenate(out_p), np.concatenate(out_t)

    def _distance(self, x: np.ndarray, node: np.ndarray, tri: np.ndarray):
        """Distances (P,) mm of the pairs, closest points and their weights on the triangles."""
        c = x[self.faces[tri]]
        q, w = closest_on_triangle(x[node], c[:, 0], c[:, 1], c[:, 2])
        return np.linalg.norm(x[node] - q, axis=1), q, w

    # -- the potential ------------------------------------------------------------------
    def evaluate(self, u: np.ndarray, pairs: Pairs | None = None, *,
                 hessian: bool = False) -> BarrierEval:
        """The barrier at ``x = X + u`` over ``pairs`` (default: those within
        ``PATTERN_MARGIN`` times the reach; the Hessian has a zero block for a pair beyond
        the reach, so that the pairs about to come into reach are in the matrix's pattern
        already and the linear solver's analysis is redone less often)."""
        if pairs is None:
            pairs, _ = self.near(u, margin=PATTERN_MARGIN if hessian else 1.0)
        x = self.X + np.asarray(u, float).reshape(-1, 3)
        grad = np.zeros(self.n_dofs)
        if len(pairs) == 0:
            return BarrierEval(0.0, grad, None, 0, np.inf)
        d, q, w = self._distance(x, pairs.node, pairs.tri)
        if np.any(d <= 0.0):
            return BarrierEval(np.inf, grad, None, len(pairs), 0.0)
        node, tri = pairs.node, pairs.tri
        b, b1, b2 = barrier(d, self.dhat)
        k = self.kappa * self.areas[node]
        n = (x[node] - q) / d[:, None]
        g = np.concatenate([n[:, None], -w[:, :, None] * n[:, None]], axis=1)   # (P, 4, 3)
        quad = np.concatenate([node[:, None], self.faces[tri]], axis=1)         # (P, 4)
        dofs = (3 * quad[:, :, None] + np.arange(3)).reshape(len(node), 12)
        np.add.at(grad, dofs, (k * b1)[:, None] * g.reshape(-1, 12))
        hess = None
        if hessian:
            gf = g.reshape(-1, 12)
            vals = np.zeros((len(node), 12, 12))
            act = np.flatnonzero(d < self.dhat)        # beyond the reach: zero blocks
            if len(act):
                Hd = distance_hessian(x[node[act]] - q[act], w[act], x[self.faces[tri[act]]])
                ga = gf[act]
                vals[act] = _psd(k[act, None, None] * (b2[act, None, None] * ga[:, :, None]
                                                       * ga[:, None, :] + b1[act, None, None] * Hd))
            rows = np.repeat(dofs, 12, axis=1).reshape(-1)
            cols = np.tile(dofs, (1, 12)).reshape(-1)
            hess = (rows, cols, vals.reshape(-1))
        act = d < self.dhat
        return BarrierEval(float(np.sum(k * b)), grad, hess, int(act.sum()),
                           float(d[act].min(initial=np.inf)))

    def check_reference(self) -> float:
        """The smallest distance (mm) between a node and a triangle outside its 2-ring in
        the reference configuration, within ``dhat`` (inf when none is that close)."""
        pairs, _ = self.near(np.zeros_like(self.X))
        if len(pairs) == 0:
            return np.inf
        return float(self._distance(self.X, pairs.node, pairs.tri)[0].min())
