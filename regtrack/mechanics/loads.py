"""Dead nodal loads: the consistent nodal forces of a surface traction, for the
``forces(t)`` of :func:`regtrack.mechanics.minimise.minimise_step` (verification problems
such as Cook's membrane, point and edge loads)."""

from __future__ import annotations

import numpy as np

from regtrack.mechanics.membrane import reference_geometry as _tri_geometry


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
