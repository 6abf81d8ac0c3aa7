"""Chest wall: the posterior cutting plane of the breast model.

The posterior boundary of the breast is the anterior face of the pectoral muscle where the
label map has a muscle label, else the posterior extent of the body.  For every
antero-posterior voxel column under the breast (columns whose breast thickness is at least
half the largest one) this boundary gives one point; a plane ``n . x = c`` is fitted to
them by least squares; its normal, projected into the axial plane (so the cranio-caudal
axis stays the patient's superior axis, along which mammographic CC compression acts),
points anterior and is the antero-posterior axis of the anatomical frame.  The plane is placed at a low percentile of the boundary points along ``n``,
so that (nearly) no muscle lies in front of it:

.. math:: c = P_q\\{ n \\cdot x_i \\} + \\Delta,

with ``q = chest_wall_percentile`` counted from the anterior side and ``Delta`` the
configured offset.  Everything posterior of the plane is removed; the nodes on it are the
fixed chest-wall nodes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from regtrack.imaging.volume import LabelVolume

log = logging.getLogger(__name__)

ANTERIOR_LPS = np.array([0.0, -1.0, 0.0])
SUPERIOR_LPS = np.array([0.0, 0.0, 1.0])


@dataclass
class Plane:
    """Plane ``{x : normal . x = offset}`` in LPS mm; ``normal`` points into the model."""

    normal: np.ndarray
    offset: float
    kind: str  # "chest_wall", "midline", "fov"

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        """Signed distance (mm), positive on the model side."""
        return np.asarray(xyz, float) @ self.normal - self.offset

    def project(self, xyz: np.ndarray) -> np.ndarray:
        return xyz - np.outer(self.distance(xyz), self.normal)

    def to_dict(self) -> dict:
        return {"normal_lps": self.normal.tolist(), "offset_mm": self.offset, "kind": self.kind}


@dataclass
class ChestWall:
    plane: Plane
    source: str  # "muscle" or "body"
    n_points: int
    tilt_deg: float
    fitted_normal: np.ndarray


def _column_faces(mask: np.ndarray, *, first: bool) -> tuple[np.ndarray, np.ndarray]:
    """(has, j) per (axis0, axis2) column: first (or last) axis-1 index holding ``mask``."""
    has = mask.any(axis=1)
    if first:
        j = np.argmax(mask, axis=1)
    else:
        j = mask.shape[1] - 1 - np.argmax(mask[:, ::-1, :], axis=1)
    return has, j


def find_chest_wall(vol: LabelVolume, body: np.ndarray, muscle: np.ndarray, *,
                    percentile: float, offset_mm: float, tilt_max_deg: float,
                    min_points: int = 50) -> ChestWall:
    """Fit the chest-wall plane of one breast (canonical orientation: axis 1 = posterior).

    Parameters
    ----------
    vol : LabelVolume
        Canonical label volume (only its geometry is used).
    body, muscle : bool arrays
        Breast body (tissue + skin + tumour) and muscle masks of the chosen half.
    percentile : float
        Percentile (%) of the boundary points, counted from the anterior side.
    offset_mm : float
        Extra anterior shift of the plane (mm).
    tilt_max_deg : float
        Fitted normals tilted more than this from the patient anterior axis are replaced
        by the patient axis (with a warning).
    """
    hb, jb_ant = _column_faces(body, first=True)
    hm, jm = _column_faces(muscle, first=True)
    hp, jb_post = _column_faces(body, first=False)
    use_muscle = hb & hm & (jm > jb_ant)
    source = "muscle" if use_muscle.sum() >= min_points else "body"
    if source == "muscle":
        valid, jpost = use_muscle, jm - 0.5
    else:
        valid, jpost = hb, jb_post + 0.5
    sp1 = vol.spacing[1]
    thick = np.where(valid, (jpost - jb_ant) * sp1, 0.0)
    foot = valid & (thick >= 0.5 * thick.max()) if valid.any() else valid
    i, k = np.nonzero(foot)
    if len(i) < 3:
        raise ValueError("chest wall: too few boundary points under the breast")
    pts = vol.index_to_world(np.stack([i, jpost[i, k], k], axis=1).astype(float))
    # least-squares plane through pts: normal = smallest principal direction
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[2]
    if n @ ANTERIOR_LPS < 0:
        n = -n
    fitted = n.copy()
    # keep the patient's superior axis: use the normal's component in the axial plane
    n = n - n[2] * SUPERIOR_LPS
    n /= np.linalg.norm(n)
    tilt = float(np.degrees(np.arccos(np.clip(n @ ANTERIOR_LPS, -1, 1))))
    if tilt > tilt_max_deg:
        log.warning("chest wall: fitted normal tilted %.1f deg from the patient anterior axis "
                    "(> chest_wall_tilt_max_deg = %.1f); using the patient axis", tilt, tilt_max_deg)
        n = ANTERIOR_LPS.copy()
    proj = pts @ n
    off = float(np.percentile(proj, 100.0 - percentile)) + offset_mm
    log.info("chest wall from %s: %d columns, tilt %.1f deg", source, len(i), tilt)
    return ChestWall(Plane(n, off, "chest_wall"), source, int(len(i)), tilt, fitted)
