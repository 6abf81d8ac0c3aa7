"""Rigid compression plates as analytic surfaces: flat faces with rounded edges.

A plate is the Minkowski sum of a *core* and a ball of radius ``r`` (the edge radius).
In the plate's local frame ``(s, t, h)`` (``s`` along ``e1``, ``t`` along ``e2``, ``h``
along the outward face normal ``N``; origin on the contact face) the core is the
semi-infinite prism

.. math::

    K = [s_0, s_1] \\times [t_0, t_1] \\times (-\\infty, -r]

so the contact face is the plane ``h = 0`` over the rectangle, and every edge is a
cylinder of radius ``r`` (the corners are spheres).  A limit may be infinite (``±inf``),
e.g. a plate whose only finite edge is the posterior (chest-wall) edge.  For a point
``x`` with local coordinates ``y``, the closest core point is
``q = (clip(s), clip(t), min(h, -r))`` and

.. math::

    g(x) = |y - q| - r, \\qquad n(x) = (y - q) / |y - q|

(the signed gap in mm, positive outside the plate, and the outward unit normal).  Over
the rectangle, ``g = h`` and ``n = N`` exactly, including below the face (the plate acts
as a half-space there, so a deeply penetrated node is always pushed back out through the
face).  The surface is C1: gap and normal are continuous across the face/edge seam.

The normal's derivative (needed by the consistent contact tangent) is

.. math::

    \\frac{\\partial n}{\\partial x} = \\frac{(I - n n^T)(I - J_q)}{|y - q|}

where ``J_q`` projects onto the local axes along which ``q`` follows ``y`` (the axes
that are not clamped); it vanishes on the flat face.

**An opening** (the compression window of an MR biopsy grid plate, through which the
needle passes): the core loses the column ``W = (a_0, a_1) x (b_0, b_1) x R``, so the
opening is the rectangle ``W`` on the face and its rim is rounded with the same radius
``r`` (at depths beyond ``r`` it narrows to ``(a_0 + r, a_1 - r) x (b_0 + r, b_1 - r)``).
A point over the opening, ``(s, t)`` in ``W``, has its closest core point on the nearest
side of ``W``: ``q = (a_k or s, t or b_k, min(h, -r))``, the exact distance to the core
(the distance from inside a rectangle to its complement is the distance to its nearest
side).  The gap is continuous; the normal turns by 90 degrees across the diagonals of the
opening, where a node would touch two sides' rims at once (only in its corners, within
``r`` of both sides).  A node inside the plate itself (penetrated deeper than ``r`` beside
the opening) is pushed back out through the face as before.

Plates only translate during a protocol (:meth:`RigidPlate.moved_to`), so the local
frame is fixed and a friction stick point stored in local coordinates follows the plate.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from regtrack.errors import ConfigError


@dataclass(frozen=True)
class PlateQuery:
    """Closest-point data of nodes against a plate (all in the model frame, mm).

    Attributes
    ----------
    gap : (N,) float
        Signed gap (mm); negative = penetration.
    normal : (N, 3) float
        Outward unit normal of the plate surface at the closest point.
    closest : (N, 3) float
        Closest point on the plate surface (mm).
    local : (N, 3) float
        Node coordinates ``(s, t, h)`` in the plate frame (mm).
    dn_dx : (N, 3, 3) float or None
        Derivative of ``normal`` with respect to the node position (1/mm).
    """

    gap: np.ndarray
    normal: np.ndarray
    closest: np.ndarray
    local: np.ndarray
    dn_dx: np.ndarray | None = None


def _unit(v, what: str) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-12:
        raise ConfigError(f"plate {what} {v.tolist()} must be a finite non-zero vector")
    return v / n


@dataclass(frozen=True)
class RigidPlate:
    """A rigid plate: flat rectangular face with cylindrical rounded edges.

    Parameters
    ----------
    name : str
        Identifier ("lower", "upper", ...), used in reports.
    origin : (3,) float
        A point of the contact face (mm, model frame).
    normal : (3,) float
        Outward unit normal of the contact face ``N``: from the plate towards the body.
    e1 : (3,) float
        In-plane direction of the first limits (made orthogonal to ``normal``).
    s_range, t_range : (float, float)
        Face limits along ``e1`` and ``e2 = normal x e1`` (mm, relative to ``origin``);
        ``-inf``/``inf`` for an unbounded side.
    edge_radius : float
        Radius of the rounded edges (mm, > 0).
    window : (s0, s1, t0, t1) or None
        A rectangular opening in the face (mm, local ``s`` and ``t`` like the ranges),
        strictly inside the face; ``None`` for a solid plate.
    """

    name: str
    origin: np.ndarray
    normal: np.ndarray
    e1: np.ndarray
    s_range: tuple[float, float] = (-np.inf, np.inf)
    t_range: tuple[float, float] = (-np.inf, np.inf)
    edge_radius: float = 10.0
    window: tuple[float, float, float, float] | None = None
    _rot: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = _unit(self.normal, f"'{self.name}' normal")
        e1 = np.asarray(self.e1, float).reshape(3)
        e1 = e1 - (e1 @ n) * n
        e1 = _unit(e1, f"'{self.name}' e1 (must not be parallel to the normal)")
        e2 = np.cross(n, e1)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "e1", e1)
        object.__setattr__(self, "origin", np.asarray(self.origin, float).reshape(3))
        object.__setattr__(self, "_rot", np.stack([e1, e2, n]))
        for nm, rg in (("s_range", self.s_range), ("t_range", self.t_range)):
            lo, hi = (float(v) for v in rg)
            if not lo < hi:
                raise ConfigError(f"plate '{self.name}' {nm} {rg}: lower limit must be < upper limit")
            object.__setattr__(self, nm, (lo, hi))
        if not (np.isfinite(self.edge_radius) and self.edge_radius > 0):
            raise ConfigError(f"plate '{self.name}' edge_radius {self.edge_radius}: must be > 0 mm")
        if self.window is not None:
            a0, a1, b0, b1 = (float(v) for v in self.window)
            if not (self.s_range[0] < a0 < a1 < self.s_range[1]
                    and self.t_range[0] < b0 < b1 < self.t_range[1]):
                raise ConfigError(f"plate '{self.name}' window {[a0, a1, b0, b1]} mm: the opening "
                                  f"must lie strictly inside the face (s {self.s_range}, "
                                  f"t {self.t_range}); move or shrink it")
            object.__setattr__(self, "window", (a0, a1, b0, b1))

    @property
    def e2(self) -> np.ndarray:
        return self._rot[1]

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rows ``e1, e2, N``: model vector -> local (s, t, h)."""
        return self._rot

    def moved_to(self, origin) -> RigidPlate:
        """The same plate translated so that its face passes through ``origin`` (mm)."""
        return replace(self, origin=np.asarray(origin, float).reshape(3))

    def translated(self, delta) -> RigidPlate:
        """The same plate translated by ``delta`` (mm)."""
        return self.moved_to(self.origin + np.asarray(delta, float).reshape(3))

    def to_local(self, x) -> np.ndarray:
        """(N, 3) model points -> (N, 3) local (s, t, h), mm."""
        return (np.asarray(x, float) - self.origin) @ self._rot.T

    def to_model(self, y) -> np.ndarray:
        """(N, 3) local (s, t, h) -> model points (mm)."""
        return np.asarray(y, float) @ self._rot + self.origin

    def query(self, x, *, curvature: bool = False) -> PlateQuery:
        """Signed gap, outward normal and closest point of every point ``x`` (N, 3), mm.

        Parameters
        ----------
        x : (N, 3) float
            Current node positions (mm, model frame).
        curvature : bool, keyword-only
            Also return ``dn_dx`` (N, 3, 3), 1/mm.
        """
        x = np.atleast_2d(np.asarray(x, float))
        r = self.edge_radius
        y = self.to_local(x)
        lo = np.array([self.s_range[0], self.t_range[0], -np.inf])
        hi = np.array([self.s_range[1], self.t_range[1], -r])
        q = np.clip(y, lo, hi)
        side = self._window_side(y)
        over = side >= 0
        if over.any():  # over the opening: the closest core point is on its nearest side
            a0, a1, b0, b1 = self.window
            k = side[over]
            qw = y[over].copy()
            qw[:, 0] = np.select([k == 0, k == 1], [a0, a1], qw[:, 0])
            qw[:, 1] = np.select([k == 2, k == 3], [b0, b1], qw[:, 1])
            qw[:, 2] = np.minimum(qw[:, 2], -r)
            q[over] = qw
        v = y - q
        rho = np.linalg.norm(v, axis=1)
        inside = rho < 1e-12 * max(r, 1.0)
        safe = np.where(inside, 1.0, rho)
        n_loc = np.where(inside[:, None], np.array([0.0, 0.0, 1.0]), v / safe[:, None])
        gap = np.where(inside, y[:, 2], rho - r)
        normal = n_loc @ self._rot
        closest = x - gap[:, None] * normal
        dn = None
        if curvature:
            free = (q == y).astype(float)  # axes along which q follows y
            free[:, 2] = np.where(y[:, 2] <= -r, 1.0, 0.0)
            proj = np.eye(3)[None] - np.einsum("ni,nj->nij", n_loc, n_loc)
            m = proj * (1.0 - free)[:, None, :] / safe[:, None, None]
            m[inside] = 0.0
            dn = np.einsum("ai,nab,bj->nij", self._rot, m, self._rot)
        return PlateQuery(gap=gap, normal=normal, closest=closest, local=y, dn_dx=dn)

    def _window_side(self, y: np.ndarray) -> np.ndarray:
        """(N,) int: for local points over the opening, its nearest side (0: s = a0,
        1: s = a1, 2: t = b0, 3: t = b1); -1 elsewhere."""
        if self.window is None:
            return np.full(len(y), -1)
        a0, a1, b0, b1 = self.window
        d = np.column_stack([y[:, 0] - a0, a1 - y[:, 0], y[:, 1] - b0, b1 - y[:, 1]])
        return np.where((d > 0).all(axis=1), d.argmin(axis=1), -1)

    def to_dict(self) -> dict:
        """JSON-ready description (mm)."""
        def lim(v: float) -> float | str:
            return v if np.isfinite(v) else ("inf" if v > 0 else "-inf")
        return {"name": self.name, "origin_mm": self.origin.tolist(),
                "normal": self.normal.tolist(), "e1": self.e1.tolist(),
                "s_range_mm": [lim(v) for v in self.s_range],
                "t_range_mm": [lim(v) for v in self.t_range],
                "edge_radius_mm": self.edge_radius,
                "window_mm": None if self.window is None else list(self.window)}
