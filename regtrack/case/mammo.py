"""Deep checks of the mammographic views of a case (DICOM header, annotations, nipple).

Only the DICOM header is read (``stop_before_pixels=True``), so a check costs
milliseconds even for 4k x 5k images.  Problems are one-line strings naming
``case.toml [views.<V>] key``; nothing is written.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from regtrack.case._paths import strip_path
from regtrack.case.annotations import read_tumour_mask, read_tumour_polygons
from regtrack.case.schema import MammogramInfo, ViewInput
from regtrack.errors import RegtrackError

log = logging.getLogger(__name__)

MODALITIES = ("MG", "DX", "CR")
#: DICOM ViewPosition values (PS3.16 CID 4014 short codes) compatible with each view
VIEW_POSITIONS = {"CC": ("CC", "XCC", "XCCL", "XCCM", "FB", "SIO"),
                  "MLO": ("MLO", "LMO", "ML", "LM", "LMO")}
SPACING_TAGS = ("PixelSpacing", "ImagerPixelSpacing")
#: relative difference above which a user spacing that differs from the tag is warned about
SPACING_RTOL = 0.01


def _spacing_tag(ds, tag: str) -> tuple[float, float] | None:
    value = getattr(ds, tag, None)
    if value is None:
        return None
    try:
        sp = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        return None
    return sp if len(sp) == 2 and min(sp) > 0 else None  # type: ignore[return-value]


def _inside(rc: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """True where (row, col) lies on the image (pixel centres at integers)."""
    rc = np.atleast_2d(rc)
    return ((rc[:, 0] >= -0.5) & (rc[:, 0] <= rows - 0.5)
            & (rc[:, 1] >= -0.5) & (rc[:, 1] <= cols - 0.5))


def _read_header(path: Path, at: str):
    import pydicom
    from pydicom.errors import InvalidDicomError

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
        for _ in ds:  # pydicom decodes lazily: surface every malformed element here
            pass
        return ds, None
    except InvalidDicomError:
        return None, (f"{at}: not a DICOM file (no 'DICM' marker); give the mammogram as "
                      "exported by the modality or PACS (MG, DX or CR)")
    except Exception as exc:  # noqa: BLE001 - pydicom raises many types on corrupt files
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
        return None, f"{at}: cannot read the DICOM header ({first}); the file may be truncated"


def _spacing(ds, view: ViewInput, at: str, at_file: str, p: list[str], w: list[str]):
    tags = {t: _spacing_tag(ds, t) for t in SPACING_TAGS}
    tag, found = next(((t, v) for t, v in tags.items() if v is not None), (None, None))
    user = view.pixel_spacing_mm
    if user is not None:
        if found is not None and not np.allclose(user, found, rtol=SPACING_RTOL):
            w.append(f"{at} pixel_spacing_mm = {list(user)} overrides the DICOM's {tag} "
                     f"{list(found)}; remove pixel_spacing_mm unless the tag is wrong")
        return tuple(user), "case.toml"
    if found is None:
        p.append(f"{at_file}: spacing missing: neither PixelSpacing nor ImagerPixelSpacing "
                 "in the DICOM; add pixel_spacing_mm = [row_mm, col_mm] to "
                 f"[views.{view.name}]")
        return None, "none"
    mag = _float(getattr(ds, "EstimatedRadiographicMagnificationFactor", None))
    if tag == "ImagerPixelSpacing" and mag is not None and mag > 0:
        # detector spacing -> spacing at the breast (as regtrack.imaging.mammogram does)
        return (found[0] / mag, found[1] / mag), f"ImagerPixelSpacing / magnification {mag:g}"
    return found, tag


def _int_tag(ds, keyword: str) -> int:
    """A single positive integer tag, else 0 (multi-valued or malformed: not an image)."""
    value = getattr(ds, keyword, None)
    try:
        return max(int(value), 0) if isinstance(value, (int, float, str)) else 0
    except (TypeError, ValueError, OverflowError):
        return 0


def _float(value) -> float | None:
    try:
        return None if value is None else float(value)
    except (TypeError, ValueError):
        return None


def _annotations(view: ViewInput, rows: int, cols: int, at: str, root: Path,
                 p: list[str]) -> int:
    try:
        if view.tumour_polygon is not None:
            polys = read_tumour_polygons(view.tumour_polygon)
            for i, poly in enumerate(polys):
                out = ~_inside(poly, rows, cols)
                if out.any():
                    k = int(np.argmax(out))
                    rel = os.path.relpath(view.tumour_polygon, root)
                    p.append(f"{at} tumour_polygon = {rel!r}: point "
                             f"{poly[k].tolist()} (row, col) of polygon {i} lies outside the "
                             f"{rows}x{cols} image; the points must be (row, col) pixels of "
                             "the mammogram's own grid")
                    break
            return len(polys)
        if view.tumour_mask is not None:
            mask = read_tumour_mask(view.tumour_mask)
            if mask.shape != (rows, cols):
                rel = os.path.relpath(view.tumour_mask, root)
                p.append(f"{at} tumour_mask = {rel!r}: {mask.shape[0]}x"
                         f"{mask.shape[1]} pixels but the mammogram has {rows}x{cols}; draw "
                         "the mask on the mammogram's own pixel grid")
                return 0
            from scipy import ndimage

            return int(ndimage.label(mask)[1])
    except RegtrackError as exc:
        key = "tumour_polygon" if view.tumour_polygon is not None else "tumour_mask"
        path = view.tumour_polygon or view.tumour_mask
        p.append(f"{at} {key} = {os.path.relpath(path, root)!r}: "  # type: ignore[arg-type]
                 f"{strip_path(str(exc), path)}")  # type: ignore[arg-type]
    return 0


def check_view(view: ViewInput, *, where: str,
               root: Path) -> tuple[MammogramInfo | None, list[str], list[str]]:
    """Check one view: DICOM header, pixel spacing, nipple and tumour annotation.

    ``root`` is the case folder (paths are shown relative to it).
    """
    at = f"{where} [views.{view.name}]"
    mammo = os.path.relpath(view.mammogram, root)
    p: list[str] = []
    w: list[str] = []
    ds, bad = _read_header(view.mammogram, f"{at} mammogram = {mammo!r}")
    if ds is None:
        return None, [bad], []  # type: ignore[list-item]
    rows, cols = _int_tag(ds, "Rows"), _int_tag(ds, "Columns")
    if rows <= 0 or cols <= 0:
        return None, [f"{at} mammogram = {mammo!r}: DICOM tag Rows/Columns missing; "
                      "this is not an image file"], []
    modality = str(getattr(ds, "Modality", "") or "")
    if modality not in MODALITIES:
        w.append(f"{at} mammogram = {mammo!r}: Modality {modality or '(none)'}, "
                 f"expected one of {', '.join(MODALITIES)}; check it is a mammogram")
    position = str(getattr(ds, "ViewPosition", "") or "").upper()
    if position and position not in VIEW_POSITIONS[view.name]:
        w.append(f"{at} mammogram = {mammo!r}: ViewPosition {position} in a "
                 f"[views.{view.name}] table; check the file belongs to this view")
    tags = (str(getattr(ds, kw, "") or "").strip().upper()
            for kw in ("ImageLaterality", "Laterality"))
    laterality = next((v for v in tags if v in ("L", "R")), "")
    spacing, source = _spacing(ds, view, at, f"{at} mammogram = {mammo!r}", p, w)
    if view.nipple_px is not None and not _inside(np.asarray(view.nipple_px), rows, cols)[0]:
        p.append(f"{at} nipple_px = {list(view.nipple_px)}: outside the {rows}x{cols} image; give "
                 "[row, col] in the mammogram's own pixel grid")
    n_tumours = _annotations(view, rows, cols, at, root, p)
    info = MammogramInfo(rows=rows, columns=cols, spacing_mm=spacing, spacing_source=source,
                         modality=modality, laterality=laterality,
                         view_position=position, tumour_polygons=n_tumours)
    return info, p, w


def check_lateralities(infos: dict[str, MammogramInfo], side: str | None, *,
                       where: str) -> tuple[list[str], list[str]]:
    """All views must show the same breast, and it must be ``[mri] side`` when given."""
    lat = {v: i.laterality for v, i in infos.items() if i.laterality in ("L", "R")}
    problems: list[str] = []
    if len(set(lat.values())) > 1:
        problems.append(f"{where} [views]: the views show different breasts ("
                        + ", ".join(f"{v}: ImageLaterality {s}" for v, s in lat.items())
                        + "); give the CC and MLO of the same breast")
    elif lat and side is not None and side not in lat.values():
        shown = next(iter(lat.values()))
        problems.append(f"{where} [mri] side = {side!r}: the mammograms show the "
                        f"{'left' if shown == 'L' else 'right'} breast (ImageLaterality "
                        f"{shown}); set side = {shown!r} or give the other breast's mammograms")
    return problems, []
