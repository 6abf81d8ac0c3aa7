r"""The chest-wall support: the breast base on the chest wall, on a layer of tissue.

The model is cut from the MRI at the chest wall.  Its chest-wall face (the plane
``x = x_cw``, normal ``+x`` in the model frame) is held normal to the wall (``u_x = 0``:
the torso is rigid) and, tangentially, lies on an elastic foundation: the shear stiffness
of a layer of the breast's own tissue ``h`` thick between the base and the body beyond
the cut (the retromammary fat),

.. math::

    \Pi_s(u) = \tfrac12 \sum_i k A_i\, |u_i - b_i|^2, \qquad k = \mu / h,
    \quad \mu = 2 \bar c_1 ,

over each node's in-wall components ``(u_y, u_z)``, with ``b_i`` the in-wall
displacement of the body on the layer's far side:

* **while the breast hangs free** (the gravity steps before the plates hold it): the body
  is at rest, ``b_i = 0``;
* **once both plates hold the breast** (from the upper plate's first touch, where the
  uncompressed thickness ``T_0`` is measured: :mod:`.protocol_run`): the body is squeezed
  with the plates, each node's ``b_i`` the plates' displacements since that touch
  interpolated by its height between them then (:func:`squeeze_weights`),

  .. math::

      b_i = (1 - w_i)\, \Delta_{lower} + w_i\, \Delta_{upper}, \qquad
      w_i = \mathrm{clip}(h_i / T_0, 0, 1).

Why: the base section is taller than the final plate gap on every exam (about 1.6 times
for a CC), so the base must move along the plates' normal as far as they squeeze it, 20 mm
and more at its top and bottom, where the tissue the model does not contain moves with
it.  A layer anchored to a body at rest sheared a few millimetres of fat by several times
its thickness, carried most of the plate force at the wall and tilted the breast; a
clamped base (the paper's model) cannot be compressed at all between plates whose faces
reach the wall; a base left free along the plates' normal has no stiffness there but its
contact with the lower plate, so that where the breast settles depends on rounding (the
flat valley measured in docs/performance.md).  The squeezed body is the load path of the
tissue beyond the cut: the layer carries the part of the breast's weight it carried when
the plates closed, and is stretched only by how far the base departs from that squeeze.

``A_i`` is the node's share of the chest-wall face (mm^2), ``k`` in N/mm^3 and ``c1`` the
tissue's mean neo-Hookean constant (MPa).  ``h -> 0`` is the clamped wall.

Units: mm, N, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WallSupport:
    """The tangential support of the chest-wall nodes,
    ``Pi_s = 1/2 sum_i k_i |u_i - b_i|^2`` over each node's in-wall ``(u_y, u_z)``.

    Attributes
    ----------
    nodes : (M,) int
        The chest-wall nodes.
    k : (M,) float
        The layer's spring stiffness ``mu A_i / h`` per node (N/mm).
    layer_mm : float
        The layer thickness ``h`` (mm).
    target : (M, 2) float or None
        ``b_i``: the in-wall displacement (mm) of the body beyond the layer (None: at rest).
    """

    nodes: np.ndarray
    k: np.ndarray
    layer_mm: float
    target: np.ndarray | None = None

    def _stretch(self, u: np.ndarray) -> np.ndarray:
        v = np.asarray(u, float).reshape(-1, 3)[self.nodes, 1:]
        return v if self.target is None else v - self.target

    def energy(self, u: np.ndarray) -> float:
        """``Pi_s`` (N mm) at the displacement ``u`` (N, 3) mm."""
        v = self._stretch(u)
        return 0.5 * float(np.sum(self.k[:, None] * v * v))

    def gradient(self, u: np.ndarray) -> np.ndarray:
        """``dPi_s/du`` (3N,) N: minus the force the support exerts on the body."""
        u = np.asarray(u, float).reshape(-1, 3)
        g = np.zeros_like(u)
        g[self.nodes, 1:] = self.k[:, None] * self._stretch(u)
        return g.reshape(-1)

    def entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(rows, cols, values)`` of ``K_s``: dof indices and N/mm, ``k_i`` on the
        diagonal of each node's ``u_y`` and ``u_z``."""
        d = (3 * self.nodes[:, None] + np.array([1, 2])[None, :]).reshape(-1)
        return d, d, np.repeat(self.k, 2)

    def moved(self, body_u: np.ndarray) -> WallSupport:
        """The support with the body beyond the layer displaced by ``body_u`` (N, 3) mm
        (its in-wall components at the chest-wall nodes)."""
        b = np.asarray(body_u, float).reshape(-1, 3)[self.nodes, 1:]  # a copy
        return WallSupport(self.nodes, self.k, self.layer_mm, b)


def squeeze_weights(x: np.ndarray, lower_origin: np.ndarray, normal: np.ndarray,
                    gap_mm: float) -> np.ndarray:
    """Where each point ``x`` (N, 3) mm lies between the plates: ``w = clip(h / gap, 0,
    1)``, ``h`` its height above the lower plate's face along the plates' ``normal``
    (lower to upper), ``gap`` the plate gap: 0 on and below the lower plate, 1 at and
    above the upper one."""
    h = (np.asarray(x, float) - np.asarray(lower_origin, float)) @ np.asarray(normal, float)
    return np.clip(h / float(gap_mm), 0.0, 1.0)


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
