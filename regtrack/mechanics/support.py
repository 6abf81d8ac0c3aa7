r"""The chest-wall support: the breast base on the chest wall, following the plates.

The model is cut from the MRI at the chest wall.  Its chest-wall face (the plane
``x = x_cw``, normal ``+x`` in the model frame) is held normal to the wall (``u_x = 0``:
the torso is rigid) and, tangentially:

* **while the breast hangs free** (the gravity steps before the plates hold it): on an
  elastic foundation, the shear stiffness of a layer of the breast's own tissue ``h``
  thick between the base and the ribs (the retromammary fat),

  .. math::

      \Pi_s(u) = \tfrac12 \sum_i k A_i (u_{iy}^2 + u_{iz}^2), \qquad k = \mu / h,
      \quad \mu = 2 \bar c_1 ;

* **once both plates hold the breast** (from the upper plate's first touch, after which
  the breast settles on the lower plate before its uncompressed thickness is measured:
  :mod:`.protocol_run`; :meth:`WallSupport.following`; the settle releases the base
  gradually, its stiffness along the normal ramped from the layer's to zero over the
  step's pseudo-time, as any load is applied): free along
  ``n_w``, the plates' normal in the wall's plane, and held across it, along
  ``t = x \times n_w``:

  .. math::

      \Pi_s(u) = \tfrac12 \sum_i F_h\, k A_i (u_i \cdot t)^2 .

Why: the base section is taller than the final plate gap on every exam (about 1.6 times
for a CC), so the base must move along the plates' normal as far as they squeeze it, 20 mm
and more at its top and bottom, where the tissue the model does not contain moves with
it.  A layer resisting that motion sheared a few millimetres of fat by several times its
thickness, carried most of the plate force at the wall and tilted the breast; a clamped
base (the paper's model) cannot be compressed at all between plates whose faces reach the
wall.  Nothing makes the base move across the plates' normal, where the body's tissue
continues past the cut on either side: there it is held, as in the paper, by the same
layer ``F_h`` = ``HELD_FACTOR`` times thinner (a penalty: it moves across by
``1 / F_h`` of what the layer would let it).

``A_i`` is the node's share of the chest-wall face (mm^2), ``k`` in N/mm^3 and ``c1`` the
tissue's mean neo-Hookean constant (MPa).  ``h -> 0`` is the clamped wall.

Units: mm, N, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: how much stiffer the base is held across the plates' normal than the layer: a layer
#: ``h / HELD_FACTOR`` thick (5 micrometres for the default 5 mm)
HELD_FACTOR = 1000.0


@dataclass(frozen=True)
class WallSupport:
    """The tangential support of the chest-wall nodes, ``Pi_s = 1/2 u^T K_s u`` with the
    2 x 2 block ``k_i U`` on each node's ``(u_y, u_z)``.

    Attributes
    ----------
    nodes : (M,) int
        The chest-wall nodes.
    k : (M,) float
        The layer's spring stiffness ``mu A_i / h`` per node (N/mm).
    layer_mm : float
        The layer thickness ``h`` (mm).
    unit : (2, 2) float
        ``U``: the identity on the layer; ``F_h t t^T`` following the plates.
    """

    nodes: np.ndarray
    k: np.ndarray
    layer_mm: float
    unit: np.ndarray = field(default_factory=lambda: np.eye(2))

    def energy(self, u: np.ndarray) -> float:
        """``Pi_s`` (N mm) at the displacement ``u`` (N, 3) mm."""
        v = np.asarray(u, float).reshape(-1, 3)[self.nodes, 1:]
        return 0.5 * float(np.sum(self.k * np.einsum("mi,ij,mj->m", v, self.unit, v)))

    def gradient(self, u: np.ndarray) -> np.ndarray:
        """``dPi_s/du`` (3N,) N: minus the force the support exerts on the body."""
        u = np.asarray(u, float).reshape(-1, 3)
        g = np.zeros_like(u)
        g[self.nodes, 1:] = self.k[:, None] * (u[self.nodes, 1:] @ self.unit.T)
        return g.reshape(-1)

    def entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(rows, cols, values)`` of ``K_s``: dof indices and N/mm, four per node (the
        same positions whatever ``unit``)."""
        d = 3 * self.nodes[:, None] + np.array([1, 2])[None, :]  # (M, 2): dofs y, z
        rows = np.repeat(d, 2, axis=1).reshape(-1)
        cols = np.tile(d, (1, 2)).reshape(-1)
        return rows, cols, (self.k[:, None, None] * self.unit[None]).reshape(-1)

    def following(self, plate_normal, released: float = 1.0) -> WallSupport:
        """The support once both plates hold the breast: free along the plates' normal
        (3,) (model frame) projected on the wall, held across it.  ``released`` in [0, 1]
        blends it with this layer, ``U = (1 - s) I + s F_h t t^T``: the release as a load
        applied over a step (the stiffness along the normal goes from the layer's to 0).  A
        normal along the wall's own (no in-wall component) leaves the layer as it is."""
        n = np.asarray(plate_normal, float)[1:]
        norm = float(np.linalg.norm(n))
        if norm < 1e-6:
            return self
        t = np.array([-n[1], n[0]]) / norm
        s = float(np.clip(released, 0.0, 1.0))
        return WallSupport(self.nodes, self.k, self.layer_mm,
                           (1.0 - s) * self.unit + s * HELD_FACTOR * np.outer(t, t))


def wall_face(points: np.ndarray, tets: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """The boundary triangles (F, 3) whose three corners are chest-wall nodes, outward
    normals (tet4 corners; a tet10 mesh's midside nodes get none)."""
    from regtrack.virtual.surface import boundary_faces

    faces = boundary_faces(np.asarray(tets)[:, :4], points)
    return faces[np.asarray(fixed, bool)[faces].all(axis=1)]


def wall_support(points: np.ndarray, tets: np.ndarray, fixed: np.ndarray, *, c1_mpa: float,
                 layer_mm: float) -> WallSupport | None:
    """The :class:`WallSupport` of the chest-wall nodes ``fixed`` (N,) bool under a layer
    ``layer_mm`` thick of tissue of neo-Hookean ``c1_mpa``; None for a clamped wall
    (``layer_mm = 0``) or a model without chest-wall nodes."""
    fixed = np.asarray(fixed, bool)
    if layer_mm <= 0 or not fixed.any():
        return None
    from regtrack.mechanics.contact import tributary_areas

    X = np.asarray(points, float)
    area = tributary_areas(X, wall_face(X, tets, fixed))
    nodes = np.flatnonzero(fixed)
    return WallSupport(nodes=nodes, k=2.0 * c1_mpa * area[nodes] / layer_mm, layer_mm=float(layer_mm))
