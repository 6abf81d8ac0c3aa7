"""Tumours: connected components of the tumour labels, with removal of specks.

Every 26-connected component of the tumour mask (benign and malignant labels together) is
one tumour.  Components smaller than ``min_volume_mm3`` are removed, with one logged
warning that lists them: real label maps carry such specks (Pelicano exam 10 has dozens of
one- to thirty-voxel "malignant" specks).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

log = logging.getLogger(__name__)


@dataclass
class Tumour:
    """One tumour component (indices in the array it was found in)."""

    id: int  # 1-based id among the kept tumours (0 for removed ones)
    label: int  # most frequent label value in the component (e.g. -3 malignant)
    n_voxels: int
    volume_mm3: float
    centroid_index: np.ndarray
    slices: tuple  # bounding box (ndimage.find_objects)
    component: int  # component number in the labelled array

    def to_dict(self) -> dict:
        return {"id": self.id, "label": self.label, "n_voxels": self.n_voxels,
                "volume_mm3": round(self.volume_mm3, 3),
                "centroid_index": [round(float(c), 2) for c in self.centroid_index]}


@dataclass
class TumourSet:
    labelled: np.ndarray  # int32 component map (0 = none)
    kept: list[Tumour]
    removed: list[Tumour]

    def mask(self, t: Tumour) -> np.ndarray:
        return self.labelled == t.component


def find_tumours(tumour_mask: np.ndarray, labels: np.ndarray, *, voxel_volume: float,
                 min_volume_mm3: float, quiet: bool = False) -> TumourSet:
    """Label tumour components; keep those of at least ``min_volume_mm3`` (mm^3).

    Kept tumours are numbered 1, 2, ... by decreasing volume.
    """
    lab, n = ndimage.label(tumour_mask, structure=np.ones((3, 3, 3), bool))
    if n == 0:
        return TumourSet(lab.astype(np.int32), [], [])
    idx = np.arange(1, n + 1)
    counts = ndimage.sum_labels(np.ones_like(lab, dtype=np.int32), lab, idx).astype(int)
    cents = np.array(ndimage.center_of_mass(tumour_mask, lab, idx)).reshape(n, 3)
    objs = ndimage.find_objects(lab)
    tumours = []
    for c in range(n):
        vals = np.rint(labels[objs[c]][lab[objs[c]] == c + 1]).astype(int)
        u, cnt = np.unique(vals, return_counts=True)
        tumours.append(Tumour(0, int(u[np.argmax(cnt)]), int(counts[c]), float(counts[c] * voxel_volume),
                              cents[c], objs[c], c + 1))
    tumours.sort(key=lambda t: -t.n_voxels)
    kept = [t for t in tumours if t.volume_mm3 >= min_volume_mm3]
    removed = [t for t in tumours if t.volume_mm3 < min_volume_mm3]
    for i, t in enumerate(kept, start=1):
        t.id = i
    if removed and not quiet:
        listing = ", ".join(f"{t.volume_mm3:.0f}" for t in removed[:30])
        more = f" (+{len(removed) - 30} more)" if len(removed) > 30 else ""
        log.warning("removed %d tumour component(s) below min_tumour_volume_mm3 = %g mm^3; "
                    "volumes (mm^3): %s%s", len(removed), min_volume_mm3, listing, more)
    lab = lab.astype(np.int32)
    return TumourSet(lab, kept, removed)
