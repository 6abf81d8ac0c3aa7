"""Canonical orientation of a mammogram: which flips/transposition bring it to the frame
of :mod:`regtrack.views` (chest wall on the left, nipple to the right, down = medial for
CC and infero-medial for MLO).

The target is the IHE Mammography display of a *left* breast: ``PatientOrientation``
``A\\R`` (LCC) and ``A\\FR`` (LMLO).  The first value of ``PatientOrientation`` names the
patient direction of increasing column index, the second that of increasing row index
(DICOM PS3.3 C.7.6.1.1.1), with letters A/P (anterior/posterior), R/L (right/left) and
H/F (head/foot).

When the tag is absent or not a valid orientation (e.g. CBIS-DDSM stores the view code
``MLO`` there), the standard IHE hanging is assumed: ``A\\R`` / ``A\\FR`` for left
breasts, ``P\\L`` / ``P\\FL`` for right breasts, i.e. only a left-right flip for right
breasts.  The caller records which rule was used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_LETTERS = set("APRLHF")


@dataclass(frozen=True)
class Orientation:
    """Map between the DICOM's own pixel grid and the canonical grid.

    The canonical image is ``flip(transpose?(source))``: first an optional transposition
    (swap rows and columns), then optional left-right and up-down flips in the
    transposed grid.

    Attributes
    ----------
    source_shape : (rows, cols) of the DICOM pixel grid.
    transpose, flip_lr, flip_ud : bool
    rule : str
        Where the orientation came from ("PatientOrientation", "IHE standard hanging",
        "image content", ...).
    """

    source_shape: tuple[int, int]
    transpose: bool = False
    flip_lr: bool = False
    flip_ud: bool = False
    rule: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the canonical grid."""
        r, c = self.source_shape
        return (c, r) if self.transpose else (r, c)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Return ``image`` (source grid, 2-D) in the canonical grid (a contiguous copy)."""
        out = image.T if self.transpose else image
        if self.flip_lr:
            out = out[:, ::-1]
        if self.flip_ud:
            out = out[::-1, :]
        return np.ascontiguousarray(out)

    def to_canonical_px(self, rc) -> np.ndarray:
        """Map (..., 2) source pixel (row, col) to canonical pixel (row, col)."""
        rc = np.asarray(rc, float)
        r, c = rc[..., 0], rc[..., 1]
        if self.transpose:
            r, c = c, r
        h, w = self.shape
        if self.flip_lr:
            c = (w - 1) - c
        if self.flip_ud:
            r = (h - 1) - r
        return np.stack([r, c], -1)

    def to_source_px(self, rc) -> np.ndarray:
        """Inverse of :meth:`to_canonical_px`."""
        rc = np.asarray(rc, float)
        r, c = rc[..., 0], rc[..., 1]
        h, w = self.shape
        if self.flip_ud:
            r = (h - 1) - r
        if self.flip_lr:
            c = (w - 1) - c
        if self.transpose:
            r, c = c, r
        return np.stack([r, c], -1)

    def with_flip_lr(self, flip_lr: bool, rule: str) -> Orientation:
        return Orientation(self.source_shape, self.transpose, flip_lr, self.flip_ud, rule)

    def with_flip_ud(self, flip_ud: bool, rule: str) -> Orientation:
        return Orientation(self.source_shape, self.transpose, self.flip_lr, flip_ud, rule)


def parse_patient_orientation(value) -> tuple[str, str] | None:
    """Return ``(column_direction, row_direction)`` or None when ``value`` is not a valid
    two-valued PatientOrientation made of the letters A, P, R, L, H, F."""
    if value is None:
        return None
    if isinstance(value, str):
        vals = value.split("\\")
    else:
        vals = [str(v) for v in value]
    vals = [v.strip().upper() for v in vals]
    if len(vals) != 2 or not all(v and set(v) <= _LETTERS for v in vals):
        return None
    return vals[0], vals[1]


def _medial(laterality: str) -> str:
    return "R" if laterality == "L" else "L"


def orientation_from_tag(po: tuple[str, str], *, shape: tuple[int, int], view: str,
                         laterality: str) -> tuple[Orientation, list[str]]:
    """Orientation that maps a grid with PatientOrientation ``po`` to the canonical one.

    Returns the orientation and notes about axes the tag did not determine (those keep
    the IHE-hanging default).
    """
    col_dir, row_dir = po
    notes: list[str] = []
    transpose = False
    if not ({"A", "P"} & set(col_dir)) and ({"A", "P"} & set(row_dir)):
        transpose = True
        col_dir, row_dir = row_dir, col_dir
    if "A" in col_dir:
        flip_lr = False
    elif "P" in col_dir:
        flip_lr = True
    else:
        flip_lr = laterality == "R"
        notes.append(f"PatientOrientation {po[0]}\\{po[1]} has no A/P axis; "
                     "left-right flip from the IHE hanging")
    if view == "MLO" and ({"H", "F"} & set(row_dir)):
        flip_ud = "H" in row_dir
    elif {"R", "L"} & set(row_dir):
        flip_ud = _medial(laterality) not in row_dir
    else:
        flip_ud = False
        notes.append(f"PatientOrientation {po[0]}\\{po[1]} does not fix the vertical axis; "
                     "kept as stored")
    rule = f"PatientOrientation {po[0]}\\{po[1]}"
    shape2 = (int(shape[0]), int(shape[1]))
    return Orientation(shape2, transpose, flip_lr, flip_ud, rule), notes


def orientation_from_hanging(*, shape: tuple[int, int], laterality: str, view: str) -> Orientation:
    """IHE standard hanging: left breasts stored as A\\R (A\\FR), right as P\\L (P\\FL)."""
    std = ("A\\R" if view == "CC" else "A\\FR") if laterality == "L" else (
        "P\\L" if view == "CC" else "P\\FL")
    return Orientation((int(shape[0]), int(shape[1])), False, laterality == "R", False,
                       f"IHE standard hanging for {laterality}{view} (stored as {std})")
