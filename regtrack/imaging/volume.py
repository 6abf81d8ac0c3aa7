"""Volumes with real-world geometry.

A volume is a numpy array indexed ``data[i, j, k]`` plus a 4x4 ``affine`` that maps the
voxel index ``(i, j, k, 1)`` to the DICOM patient frame (LPS, mm)::

    x_LPS = affine @ [i, j, k, 1]

so ``affine[:3, :3] = direction @ diag(spacing)`` and ``affine[:3, 3]`` is the centre of
voxel (0, 0, 0).  This is the convention of ITK/SimpleITK (origin, spacing, direction),
with the index order of the numpy array matching the ITK index order (i fastest in ITK is
the *first* numpy axis here; readers transpose as needed).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


def make_affine(origin, spacing, direction=None) -> np.ndarray:
    """4x4 voxel-to-LPS affine from ITK-style origin (mm), spacing (mm) and 3x3 direction.

    ``direction[:, a]`` is the unit LPS vector of array axis ``a``.
    """
    d = np.eye(3) if direction is None else np.asarray(direction, float).reshape(3, 3)
    a = np.eye(4)
    a[:3, :3] = d @ np.diag(np.asarray(spacing, float))
    a[:3, 3] = np.asarray(origin, float)
    return a


@dataclass
class Volume:
    """A 3-D array with its voxel-to-patient (LPS, mm) affine."""

    data: np.ndarray
    affine: np.ndarray
    source: Path | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.affine = np.asarray(self.affine, dtype=float)
        if self.data.ndim != 3:
            raise ValueError(f"volume data must be 3-D, got shape {self.data.shape}")
        if self.affine.shape != (4, 4):
            raise ValueError(f"affine must be 4x4, got {self.affine.shape}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along each array axis (mm)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def direction(self) -> np.ndarray:
        """3x3 matrix whose columns are the unit LPS directions of the array axes."""
        return self.affine[:3, :3] / self.spacing

    @property
    def origin(self) -> np.ndarray:
        """LPS position (mm) of the centre of voxel (0, 0, 0)."""
        return self.affine[:3, 3].copy()

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel (mm^3)."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))

    def index_to_world(self, ijk) -> np.ndarray:
        """Map voxel indices (..., 3) to LPS mm (..., 3)."""
        ijk = np.asarray(ijk, float)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_index(self, xyz) -> np.ndarray:
        """Map LPS mm (..., 3) to continuous voxel indices (..., 3)."""
        xyz = np.asarray(xyz, float)
        inv = np.linalg.inv(self.affine)
        return xyz @ inv[:3, :3].T + inv[:3, 3]

    def crop(self, lo, hi) -> "Volume":
        """Sub-volume ``data[lo0:hi0, lo1:hi1, lo2:hi2]`` with its affine shifted to match."""
        lo = np.maximum(np.asarray(lo, int), 0)
        hi = np.minimum(np.asarray(hi, int), self.shape)
        sub = self.data[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        aff = self.affine.copy()
        aff[:3, 3] = self.index_to_world(lo)
        return type(self)(sub.copy(), aff, self.source, dict(self.meta))


@dataclass
class LabelVolume(Volume):
    """Integer label map (see ``regtrack.case`` for the label values of a case)."""

    def __post_init__(self) -> None:
        super().__post_init__()


@dataclass
class ImageVolume(Volume):
    """Intensity volume (e.g. an MRI series), float data."""
