"""Readers of the tumour annotations of a mammogram (polygon JSON or binary mask).

Polygon JSON, in the DICOM's own pixel grid (row, col; pixel centres at integers)::

    {"points_rc": [[row, col], [row, col], ...]}             # one tumour
    {"polygons_rc": [[[row, col], ...], [[row, col], ...]]}  # several tumours

Each polygon has at least 3 points, is closed implicitly (first point not repeated) and
must be simple (no self-intersection) with a non-zero area.  A mask is a 2-D image with
the DICOM's Rows x Columns, zero outside the tumour(s) and one other value inside.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from regtrack.errors import InputFileError


def _polygon(points, path: Path, label: str) -> np.ndarray:
    try:
        arr = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise InputFileError(f"{path}: {label} must be a list of [row, col] number pairs") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputFileError(f"{path}: {label} must be a list of [row, col] pairs, got an array "
                             f"of shape {arr.shape}")
    if len(arr) < 3:
        raise InputFileError(f"{path}: {label} has {len(arr)} point(s); a polygon needs at least 3")
    if not np.all(np.isfinite(arr)):
        raise InputFileError(f"{path}: {label} has NaN or infinite coordinates")
    if len(arr) > 3 and np.allclose(arr[0], arr[-1]):
        arr = arr[:-1]  # tolerate an explicitly closed ring
    return arr


def check_polygon_shape(poly: np.ndarray) -> str | None:
    """None if ``poly`` (K, 2) is a simple polygon of non-zero area, else the reason."""
    from shapely.geometry import Polygon
    from shapely.validation import explain_validity

    shape = Polygon(poly[:, ::-1])
    if shape.area <= 0:
        return "has zero area (collinear or repeated points, or a symmetric bow tie)"
    if not shape.is_valid:
        return f"is not a simple polygon ({explain_validity(shape)}); reorder the points"
    return None


def read_tumour_polygons(path: str | Path) -> list[np.ndarray]:
    """Read a tumour polygon JSON file.

    Returns
    -------
    list of (K, 2) float arrays
        Polygons as ``(row, col)`` pixel coordinates of the DICOM grid.

    Raises
    ------
    InputFileError
        Unreadable JSON, missing ``points_rc`` / ``polygons_rc``, fewer than 3 points,
        non-finite values, a self-intersecting or zero-area polygon.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(f"{path}: invalid JSON ({exc}); fix the file") from None
    if not isinstance(doc, dict) or not ({"points_rc", "polygons_rc"} & set(doc)):
        raise InputFileError(f'{path}: expected an object with "points_rc": [[row, col], ...] '
                             'or "polygons_rc": [[[row, col], ...], ...]')
    if "points_rc" in doc and "polygons_rc" in doc:
        raise InputFileError(f'{path}: give "points_rc" or "polygons_rc", not both')
    if "points_rc" in doc:
        polys = [_polygon(doc["points_rc"], path, "points_rc")]
    else:
        raw = doc["polygons_rc"]
        if not isinstance(raw, list) or not raw:
            raise InputFileError(f"{path}: polygons_rc must be a non-empty list of polygons")
        polys = [_polygon(p, path, f"polygons_rc[{i}]") for i, p in enumerate(raw)]
    for i, poly in enumerate(polys):
        bad = check_polygon_shape(poly)
        if bad:
            label = "points_rc" if "points_rc" in doc else f"polygons_rc[{i}]"
            raise InputFileError(f"{path}: {label} {bad}")
    return polys


def read_tumour_mask(path: str | Path) -> np.ndarray:
    """Read a binary tumour mask image as a boolean (rows, cols) array.

    Raises
    ------
    InputFileError
        Unreadable image, not 2-D (colour images are refused, so a screenshot is not taken
        for a mask), more than two distinct values, or no tumour pixel.
    """
    import cv2

    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputFileError(f"{path}: cannot read the image; save the mask as PNG or TIFF")
    if img.ndim != 2:
        raise InputFileError(f"{path}: {img.ndim}-D image with {img.shape[-1]} channels; save "
                             "the mask as a single-channel (grey) image")
    values = np.unique(img)
    if len(values) > 2 or (len(values) == 2 and values[0] != 0):
        raise InputFileError(f"{path}: {len(values)} distinct values {values[:5].tolist()}; a "
                             "mask holds 0 outside the tumour and one value inside")
    mask = img != 0
    if not mask.any():
        raise InputFileError(f"{path}: the mask is empty (all zero); mark the tumour pixels")
    return mask
