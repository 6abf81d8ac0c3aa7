"""The finite-element breast model passed from meshing to mechanics.

Model frame
-----------
Points are stored in mm in the *anatomical model frame*, a proper rotation + translation
of the DICOM patient frame (LPS):

* origin: the nipple (undeformed, prone MRI configuration);
* ``x``: antero-posterior axis, pointing **anterior** (from the chest wall to the nipple);
* ``y``: cranio-caudal axis, pointing **superior** (cranial);
* ``z = x * y``: points to the patient's **right** for both breasts, so the lateral
  direction is ``+z`` for a right breast and ``-z`` for a left breast
  (:attr:`AnatomicalFrame.lateral_sign`).

In the prone MRI, gravity acts along ``+x`` (towards the table); standing, along ``-y``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TISSUE = 1
TUMOUR = 2
SKIN = 3


@dataclass
class AnatomicalFrame:
    """Rigid map between LPS (mm) and the model frame.

    ``axes`` rows are the model x, y, z unit vectors expressed in LPS; ``origin`` is the
    LPS position of the model origin (the nipple).  ``x_model = axes @ (x_lps - origin)``.
    """

    origin: np.ndarray
    axes: np.ndarray
    side: str  # "L" or "R": which breast

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, float).reshape(3)
        self.axes = np.asarray(self.axes, float).reshape(3, 3)
        if self.side not in ("L", "R"):
            raise ValueError(f"side must be 'L' or 'R', got {self.side!r}")
        if not np.allclose(self.axes @ self.axes.T, np.eye(3), atol=1e-6) or np.linalg.det(
            self.axes
        ) < 0:
            raise ValueError("frame axes must be a proper rotation (orthonormal, det +1)")

    @property
    def lateral_sign(self) -> float:
        """+1 when lateral is +z (right breast), -1 for a left breast."""
        return 1.0 if self.side == "R" else -1.0

    def to_model(self, xyz_lps) -> np.ndarray:
        return (np.asarray(xyz_lps, float) - self.origin) @ self.axes.T

    def to_patient(self, xyz_model) -> np.ndarray:
        return np.asarray(xyz_model, float) @ self.axes + self.origin

    def to_dict(self) -> dict:
        return {"origin_lps": self.origin.tolist(), "axes_lps": self.axes.tolist(), "side": self.side}

    @classmethod
    def from_dict(cls, d: dict) -> "AnatomicalFrame":
        return cls(np.array(d["origin_lps"]), np.array(d["axes_lps"]), d["side"])

    @classmethod
    def standard(cls, side: str, origin_lps=(0.0, 0.0, 0.0)) -> "AnatomicalFrame":
        """Frame aligned with the patient axes: x anterior (-P), y superior (+S), z right (-L)."""
        axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
        return cls(np.asarray(origin_lps, float), axes, side)


@dataclass
class BreastModel:
    """Tetrahedral breast model in the model frame (mm).

    Attributes
    ----------
    points : (N, 3) float
        Node coordinates (mm, model frame).
    tets : (E, 4) int
        Linear tetrahedra, positively oriented.
    region : (E,) int
        1 tissue, 2 tumour.
    tumour_id : (E,) int
        0 for tissue, k >= 1 for the k-th tumour.
    skin : (S, 3) int
        Outer-surface triangles (skin membrane, region 3), chest-wall face excluded;
        oriented with outward normals.
    fixed : (N,) bool
        Chest-wall nodes (all displacement components fixed).
    nipple : int
        Index of the nipple node.
    frame : AnatomicalFrame
    tissue_label : (E,) int or None
        Detailed label per element (fat/gland classes) for heterogeneous models.
    meta : dict
        Provenance, settings and mesh-quality figures.
    """

    points: np.ndarray
    tets: np.ndarray
    region: np.ndarray
    tumour_id: np.ndarray
    skin: np.ndarray
    fixed: np.ndarray
    nipple: int
    frame: AnatomicalFrame
    tissue_label: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, float)
        self.tets = np.asarray(self.tets, np.int64)
        self.region = np.asarray(self.region, np.int64)
        self.tumour_id = np.asarray(self.tumour_id, np.int64)
        self.skin = np.asarray(self.skin, np.int64).reshape(-1, 3)
        self.fixed = np.asarray(self.fixed, bool)
        self.nipple = int(self.nipple)

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def tet_volumes(self, points: np.ndarray | None = None) -> np.ndarray:
        """Signed tetrahedron volumes (mm^3) for ``points`` (default: reference)."""
        x = self.points if points is None else points
        p = x[self.tets]
        return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0

    def tumour_centroids(self) -> dict[int, np.ndarray]:
        """Volume-weighted centroid (mm, model frame, reference configuration) of each
        tumour id (elements of the tumour region without an id count as tumour 1)."""
        out = {}
        sel = self.region == TUMOUR
        vol = np.abs(self.tet_volumes())
        ids = np.where(sel & (self.tumour_id <= 0), 1, self.tumour_id)
        for k in np.unique(ids[sel]):
            m = sel & (ids == k)
            out[int(k)] = (vol[m] @ self.points[self.tets[m]].mean(axis=1)) / vol[m].sum()
        return out
