"""Dead nodal loads as a :class:`~regtrack.mechanics.contributions.Contribution`.

``NodalForces(forces)`` adds ``r(u) = -t * forces`` to the residual during a step
(``t`` the step's pseudo-time), i.e. a prescribed force ramped from 0 to ``forces``
(N, 3) in N.  Used for verification problems (Cook's membrane) and point/edge loads.
"""

from __future__ import annotations

import numpy as np

from regtrack.mechanics.membrane import reference_geometry as _tri_geometry


class NodalForces:
    """Dead (non-follower) nodal forces ramped with the step's pseudo-time."""

    def __init__(self, forces: np.ndarray, *, name: str = "nodal_forces", start: np.ndarray | None = None):
        self.name = name
        self.forces = np.asarray(forces, float).reshape(-1, 3)
        self.start = np.zeros_like(self.forces) if start is None else np.asarray(start, float).reshape(-1, 3)
        self.t = 0.0

    def begin_step(self, step) -> None:
        self.t = 0.0

    def set_time(self, t: float) -> None:
        self.t = float(t)

    def current(self) -> np.ndarray:
        return self.start + self.t * (self.forces - self.start)

    def residual_tangent(self, u: np.ndarray):
        return -self.current().reshape(-1), None

    def commit(self, u: np.ndarray) -> None:
        pass

    def rollback(self) -> None:
        pass

    def augment(self, u: np.ndarray) -> bool:
        return True

    def report(self, u: np.ndarray) -> dict:
        return {"total_force_n": self.current().sum(axis=0).tolist()}


def traction_forces(points: np.ndarray, tris: np.ndarray, traction: np.ndarray) -> np.ndarray:
    """Consistent nodal forces (N, 3) N of a uniform traction (MPa, reference area).

    Linear triangles (T, 3): each node receives ``A / 3 * traction``.  Straight-sided
    6-node triangles (T, 6; corners then mid-edge nodes): corners 0, mid-edge nodes
    ``A / 3`` (the integrals of the quadratic shape functions).
    """
    tris = np.asarray(tris)
    _, area = _tri_geometry(points, tris[:, :3])
    f = np.zeros((len(points), 3))
    cols = range(3) if tris.shape[1] == 3 else range(3, 6)
    for a in cols:
        np.add.at(f, tris[:, a], area[:, None] / 3.0 * np.asarray(traction, float)[None, :])
    return f
