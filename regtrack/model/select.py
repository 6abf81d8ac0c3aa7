"""Breast selection: reorient the label map to LPS axes, split a bilateral map at the
midline and choose the breast to model.

The canonical array orientation used by the model package is "LPS-aligned": array axis 0
points to the patient's left, axis 1 posterior, axis 2 superior (:func:`reorient_lps`).
The midline is the valley of the anterior body profile between the two breasts
(:func:`find_midline`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal

from regtrack.errors import InputFileError
from regtrack.imaging.volume import LabelVolume

log = logging.getLogger(__name__)


def reorient_lps(vol: LabelVolume) -> LabelVolume:
    """Permute and flip array axes so that axis ``k`` points along +LPS axis ``k``.

    Only axes are permuted/flipped (no resampling); an oblique volume keeps its obliquity
    in the affine.  The world position of every voxel is unchanged.
    """
    d = vol.direction
    perm = [int(np.argmax(np.abs(d[k]))) for k in range(3)]
    if sorted(perm) != [0, 1, 2]:
        raise InputFileError(f"{vol.source}: label map direction matrix {d.round(3).tolist()} "
                             "is too oblique to identify its patient axes")
    data = np.transpose(vol.data, perm)
    aff = np.eye(4)
    old_index0 = np.zeros(3)
    for k, a in enumerate(perm):
        col = vol.affine[:3, a].copy()
        if d[k, a] < 0:
            data = np.flip(data, axis=k)
            old_index0[a] = vol.shape[a] - 1
            col = -col
        aff[:3, k] = col
    aff[:3, 3] = vol.index_to_world(old_index0)
    return LabelVolume(np.ascontiguousarray(data), aff, vol.source, dict(vol.meta))


@dataclass
class Midline:
    """Result of :func:`find_midline` (canonical orientation, axis 0 = patient left)."""

    bilateral: bool
    index: int | None  # first voxel index (axis 0) of the patient-left half
    peaks: tuple[int, ...]  # axis-0 indices of the breast apexes found
    prominence_mm: float


def anterior_profile(body: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Anterior extent (mm, larger = more anterior) of the body for each axis-0 column.

    ``-inf`` where a column holds no body voxel.
    """
    any_ij = body.any(axis=2)
    first = np.argmax(any_ij, axis=1).astype(float)
    prof = -first * spacing[1]
    prof[~any_ij.any(axis=1)] = -np.inf
    return prof


def find_midline(body: np.ndarray, spacing: np.ndarray, *, min_prominence_mm: float) -> Midline:
    """Split a canonical body mask between the two breasts.

    The anterior profile :func:`anterior_profile` is smoothed (sigma 3 mm); two peaks more
    prominent than ``min_prominence_mm`` are the breasts and the deepest point between
    them is the midline.  Fewer peaks: a unilateral map.
    """
    prof = anterior_profile(body, spacing)
    valid = np.isfinite(prof)
    if not valid.any():
        return Midline(False, None, (), 0.0)
    filled = np.where(valid, prof, prof[valid].min() - 50.0)
    sm = ndimage.gaussian_filter1d(filled, 3.0 / spacing[0])
    peaks, props = signal.find_peaks(sm, prominence=min_prominence_mm)
    if len(peaks) < 2:
        return Midline(False, None, tuple(int(p) for p in peaks), float(props["prominences"].max()) if len(peaks) else 0.0)
    top = np.sort(peaks[np.argsort(props["prominences"])[-2:]])
    a, b = int(top[0]), int(top[1])
    m = a + int(np.argmin(sm[a : b + 1]))
    prom = float(min(sm[a], sm[b]) - sm[m])
    return Midline(True, m, (a, b), prom)


def side_slices(shape: tuple[int, ...], midline: Midline, side: str) -> slice:
    """Axis-0 slice of the half holding breast ``side`` ("R" = low axis-0 indices)."""
    if not midline.bilateral:
        return slice(0, shape[0])
    return slice(0, midline.index) if side == "R" else slice(midline.index, shape[0])


def check_side(side: str | None, *, where: str = "side") -> str | None:
    """Validate a side value ("L"/"R", case-insensitive; None allowed)."""
    if side is None:
        return None
    s = str(side).strip().upper()
    if s in ("LEFT", "RIGHT"):
        s = s[0]
    if s not in ("L", "R"):
        raise InputFileError(f"{where} = {side!r}: must be 'L' or 'R'")
    return s


def unilateral_side(vol: LabelVolume, body: np.ndarray) -> tuple[str, float]:
    """Side of a one-breast map from the LPS x (left) coordinate of the body centroid.

    Returns ``(side, centroid_left_mm)``; the DICOM patient frame has its x axis towards
    the patient's left with the scanner isocentre near the midline.
    """
    idx = np.argwhere(body)
    c = vol.index_to_world(idx.mean(axis=0))
    return ("L" if c[0] > 0 else "R"), float(c[0])
