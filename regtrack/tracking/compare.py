"""The simulated compression against an imaged compressed MRI (Chung et al. 2008).

Two measures, both in the MRI's patient frame (LPS, mm):

* **Surface distance.** For every skin node of the simulated compressed breast, the
  distance to the imaged compressed skin, the boundary of the breast voxels (the case's
  label scheme, classes tissue + skin + tumour) of a label map of the compressed MRI.  The
  imaged surface is the marching-cubes isosurface (:func:`skimage.measure.marching_cubes`,
  level 0.5 of the binary mask) sampled at its vertices and face centroids; a node's
  distance is that to the nearest sample (:class:`scipy.spatial.cKDTree`), which
  overestimates the distance to the surface by at most about half the sample spacing
  squared over twice the distance.  Reported: RMS, mean, 95th percentile and maximum
  (Chung et al. report the RMS, 1.5 mm).
* **Landmark distances.** The simulated position of each MRI landmark
  (:class:`~regtrack.tracking.deformation.DeformationMap`) against the same landmark
  picked in the compressed MRI, matched by name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regtrack.errors import TrackingError
from regtrack.imaging.volume import LabelVolume


@dataclass(frozen=True)
class SurfaceDistance:
    """Distances (mm) from the simulated skin nodes to the imaged compressed skin."""

    rms_mm: float
    mean_mm: float
    p95_mm: float
    max_mm: float
    n_points: int

    def to_dict(self) -> dict:
        return {"rms_mm": self.rms_mm, "mean_mm": self.mean_mm, "p95_mm": self.p95_mm,
                "max_mm": self.max_mm, "n_points": self.n_points}


def imaged_surface(labels: LabelVolume, mask: np.ndarray) -> np.ndarray:
    """(V, 3) LPS samples (mm) of the boundary of ``mask`` (bool, the label map's grid):
    the marching-cubes vertices and face centroids."""
    from skimage.measure import marching_cubes

    if not mask.any():
        raise TrackingError("the compressed label map holds no breast voxel (tissue, skin or "
                            "tumour of the case's label scheme); give the compressed breast's "
                            "label map")
    verts, faces, _, _ = marching_cubes(np.pad(mask, 1).astype(np.uint8), level=0.5)
    idx = np.vstack([verts, verts[faces].mean(axis=1)]) - 1.0  # undo the padding
    return idx @ labels.affine[:3, :3].T + labels.affine[:3, 3]


def surface_distance(points_lps: np.ndarray, surface_lps: np.ndarray) -> SurfaceDistance:
    """Distance statistics (mm) of ``points_lps`` (M, 3) to the surface samples."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(surface_lps).query(np.asarray(points_lps, float))
    return SurfaceDistance(rms_mm=float(np.sqrt(np.mean(d ** 2))), mean_mm=float(d.mean()),
                           p95_mm=float(np.percentile(d, 95)), max_mm=float(d.max()),
                           n_points=int(len(d)))


def skin_distance(model, deformed: np.ndarray, labels: LabelVolume, scheme) -> SurfaceDistance:
    """Surface distance of the simulated compressed skin (``deformed`` model-frame node
    positions, mm) to the breast of the imaged compressed ``labels``."""
    nodes = np.unique(model.skin)
    pts = model.frame.to_patient(np.asarray(deformed, float)[nodes])
    return surface_distance(pts, imaged_surface(labels, scheme.mask(labels.data, "body")))


def landmark_distances(names, predicted_lps: np.ndarray, observed) -> list[dict]:
    """Distance (mm) between each predicted landmark and the one of the same name in
    ``observed`` (:class:`~regtrack.tracking.landmarks.Landmarks` of the compressed MRI)."""
    where = dict(zip(observed.names, observed.lps_mm))
    missing = [n for n in names if n not in where]
    if missing:
        raise TrackingError(f"landmark {missing[0]!r} is not in the compressed MRI's landmark "
                            f"file (names there: {', '.join(observed.names)}); give both "
                            "files the same names")
    out = []
    for n, p in zip(names, np.asarray(predicted_lps, float)):
        q = np.asarray(where[n], float)
        out.append({"name": n, "predicted_lps_mm": p.tolist(), "observed_lps_mm": q.tolist(),
                    "distance_mm": float(np.linalg.norm(p - q))})
    return out
