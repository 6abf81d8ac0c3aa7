"""Deep checks of the MRI inputs of a case: label map values, nipple point, DICOM series.

These open the files (read-only) and report problems as one-line strings naming
``case.toml [section] key``; they never raise for a bad input and never write anything.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from regtrack.case._paths import strip_path
from regtrack.case.schema import LabelMapInfo, MriInput
from regtrack.errors import RegtrackError
from regtrack.imaging.volume import LabelVolume
from regtrack.model.labels import CLASSES

log = logging.getLogger(__name__)

#: Classes that must occur in the label map (the model needs tissue and a tumour to track).
REQUIRED_CLASSES = ("tissue", "tumour")


def _fmt(values) -> str:
    return ", ".join(str(int(v)) for v in values) or "(none)"


def read_label_volume(path: Path) -> LabelVolume:
    """Read a label map with :func:`regtrack.imaging.readers.read_label_map` (imported
    lazily: it pulls in SimpleITK)."""
    from regtrack.imaging.readers import read_label_map

    return read_label_map(path)


def _label_counts(data: np.ndarray) -> dict[int, int]:
    """Voxel count of each label value (the reader guarantees integer labels)."""
    values, counts = np.unique(data, return_counts=True)
    return {int(v): int(c) for v, c in zip(values, counts)}


def check_label_values(counts: dict[int, int], mri: MriInput, *, where: str,
                       name: str) -> tuple[list[str], list[str]]:
    """Compare the label values present (``counts``) with the case's label scheme.

    Problems: a value present in the map that belongs to no class (wrong scheme), no
    voxel of a required class (:data:`REQUIRED_CLASSES`).  Warnings: no voxel of an
    optional class (skin, muscle, background), a value listed in ``[mri.label_values]``
    that does not occur.
    """
    problems: list[str] = []
    warnings: list[str] = []
    scheme = mri.scheme
    key = "[mri] scheme" if mri.scheme_name is not None else "[mri.label_values]"
    if mri.scheme_name is not None:
        key += f" = {mri.scheme_name!r}"
    present = sorted(counts)
    known = {v for c in CLASSES for v in getattr(scheme, c)}
    unknown = [v for v in present if v not in known]
    absent: list[str] = []  # required classes without a voxel
    for cls in CLASSES:
        values = getattr(scheme, cls)
        if not values:
            continue
        found = [v for v in values if v in counts]
        if not found:
            if cls in REQUIRED_CLASSES:
                absent.append(f"{cls} = {list(values)}")
            else:
                warnings.append(f"{where} [mri.label_values] {cls} = {list(values)}: no voxel "
                                f"of {name} has these values (values present: {_fmt(present)})")
        elif cls in mri.explicit_classes:
            missing = [v for v in values if v not in counts]
            if missing:
                warnings.append(f"{where} [mri.label_values] {cls}: value(s) {_fmt(missing)} do "
                                f"not occur in {name}")
    if unknown:  # most likely the wrong scheme: one line says it all
        also = f", and no voxel has {' or '.join(absent)}" if absent else ""
        problems.append(
            f"{where} {key}: label value(s) {_fmt(unknown)} of {name} belong to no class{also} "
            f"(values present: {_fmt(present)}); add them to [mri.label_values] or choose "
            "another scheme")
    else:
        problems += [f"{where} [mri.label_values] {a}: no voxel of {name} has these values "
                     f"(values present: {_fmt(present)}); fix the label values or the scheme"
                     for a in absent]
    return problems, warnings


def check_nipple(vol: LabelVolume, nipple_lps_mm, *, where: str, name: str) -> list[str]:
    """``[mri] nipple_lps_mm`` must lie inside the label map's voxel grid."""
    ijk = vol.world_to_index(np.asarray(nipple_lps_mm, float))
    shape = np.asarray(vol.shape)
    if np.all(ijk >= -0.5) and np.all(ijk <= shape - 0.5):
        return []
    corners = vol.index_to_world(np.array([[-0.5] * 3, list(shape - 0.5)]))
    lo, hi = corners.min(0), corners.max(0)
    return [f"{where} [mri] nipple_lps_mm = {list(nipple_lps_mm)}: outside {name} (LPS extent "
            f"{np.round(lo, 1).tolist()} to {np.round(hi, 1).tolist()} mm); give the nipple in "
            "the label map's patient coordinates (LPS, mm)"]


def check_label_map(mri: MriInput, *, where: str,
                    root: Path) -> tuple[LabelMapInfo | None, list[str], list[str]]:
    """Open the label map of ``mri`` and check its values and the nipple point.

    ``root`` is the case folder (paths are shown relative to it).
    """
    rel = os.path.relpath(mri.labels, root)
    name = f"'{rel}'"
    at = f"{where} [mri] labels = {rel!r}"
    try:
        vol = read_label_volume(mri.labels)
    except RegtrackError as exc:
        return None, [f"{at}: {strip_path(str(exc), mri.labels)}"], []
    except (OSError, RuntimeError, ValueError) as exc:  # SimpleITK raises RuntimeError
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return None, [f"{at}: cannot read the label map ({first}); check the file is a "
                      "complete NIfTI/MHA/NRRD image"], []
    counts = _label_counts(vol.data)
    problems, warnings = check_label_values(counts, mri, where=where, name=name)
    if mri.nipple_lps_mm is not None:
        problems += check_nipple(vol, mri.nipple_lps_mm, where=where, name=name)
    info = LabelMapInfo(shape=vol.shape, spacing_mm=tuple(float(s) for s in vol.spacing),  # type: ignore[arg-type]
                        origin_lps_mm=tuple(float(o) for o in vol.origin), counts=counts,
                        affine=vol.affine.copy())
    return info, problems, warnings


def _corners(affine: np.ndarray, shape) -> np.ndarray:
    n = np.asarray(shape) - 1
    idx = np.array([[i, j, k] for i in (0, n[0]) for j in (0, n[1]) for k in (0, n[2])], float)
    return idx @ affine[:3, :3].T + affine[:3, 3]


def check_series(series: Path, label_map: LabelMapInfo | None, *, where: str,
                 root: Path) -> tuple[list[str], list[str]]:
    """The DICOM MR series must be readable and share the label map's voxel grid.

    The grids match when the shapes are equal and the eight corner voxel centres agree to
    within half the largest voxel size (the label map must be segmented on this series).
    """
    from regtrack.imaging.dicom_series import read_dicom_series

    at = f"{where} [mri] series = {os.path.relpath(series, root)!r}"
    try:
        data, affine, _ = read_dicom_series(series)
    except RegtrackError as exc:
        return [f"{at}: {strip_path(str(exc), series)}"], []
    if label_map is None:
        return [], []
    lab_affine, lab_shape = label_map.affine, label_map.shape
    if tuple(data.shape) != tuple(lab_shape):
        return [f"{at}: {data.shape[0]}x{data.shape[1]}x{data.shape[2]} voxels but the label map "
                f"has {lab_shape[0]}x{lab_shape[1]}x{lab_shape[2]}; the label map must be "
                "segmented on this series (same grid)"], []
    off = np.linalg.norm(_corners(affine, data.shape) - _corners(lab_affine, lab_shape), axis=1)
    tol = 0.5 * float(np.linalg.norm(lab_affine[:3, :3], axis=0).max())
    if off.max() > tol:
        return [f"{at}: voxel grid is {off.max():.2f} mm away from the label map's (tolerance "
                f"{tol:.2f} mm); the label map must be segmented on this series (same origin, "
                "spacing and orientation)"], []
    return [], []
