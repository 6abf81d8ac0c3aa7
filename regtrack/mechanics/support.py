"""The chest-wall support: the breast base slides on the chest wall over a soft layer.

The breast is not welded to the ribs: its base lies on the pectoral fascia over the
retromammary fat, a loose layer that lets it glide over the chest wall.  The nodes of the
model's chest-wall face (its cut at the chest wall, the plane ``x = x_cw`` with normal
``+x`` in the model frame) are held normal to the wall (``u_x = 0``: the torso is rigid)
and tangentially by an elastic foundation, the shear stiffness of a layer of the breast's
own tissue ``h`` thick between the base and the ribs:

.. math::

    \\Pi_s(u) = \\tfrac12 \\sum_i k A_i (u_{iy}^2 + u_{iz}^2), \\qquad k = \\mu / h,
    \\quad \\mu = 2 \\bar c_1

(N mm), ``A_i`` the node's share of the chest-wall face (mm^2), ``k`` in N/mm^3 and
``c1`` the tissue's mean neo-Hookean constant (MPa).  ``h -> 0`` is the clamped wall of
the paper's model; ``h -> inf`` a frictionless sliding wall, on which the breast slides
out between the plates.  The clamped base cannot follow the plates: the models are cut
from the MRI at the chest wall, so the fixed section is about 1.6 times as tall as the
final CC plate gap (docs/performance.md), and the tissue between the plates' edges and
the clamped nodes is squeezed without limit.  The layer lets the base shear by what the
plates demand, against a stiffness that scales with the tissue's.

Units: mm, N, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WallSupport:
    """The tangential foundation of the chest-wall nodes.

    Attributes
    ----------
    dofs : (M,) int
        The tangential (``y``, ``z``) dofs of the chest-wall nodes.
    k : (M,) float
        Their spring stiffness ``mu A_i / h`` (N/mm).
    layer_mm : float
        The layer thickness ``h`` (mm).
    """

    dofs: np.ndarray
    k: np.ndarray
    layer_mm: float

    def energy(self, u: np.ndarray) -> float:
        """``Pi_s`` (N mm) at the displacement ``u`` (N, 3) mm."""
        v = np.asarray(u, float).reshape(-1)[self.dofs]
        return 0.5 * float(np.sum(self.k * v * v))

    def gradient(self, u: np.ndarray) -> np.ndarray:
        """``dPi_s/du`` (3N,) N: minus the force the layer exerts on the body."""
        g = np.zeros(np.asarray(u).size)
        g[self.dofs] = self.k * np.asarray(u, float).reshape(-1)[self.dofs]
        return g


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
    k = 2.0 * c1_mpa * area[nodes] / layer_mm
    dofs = np.concatenate([3 * nodes + 1, 3 * nodes + 2])
    return WallSupport(dofs=dofs, k=np.concatenate([k, k]), layer_mm=float(layer_mm))
