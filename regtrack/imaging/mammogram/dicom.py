"""Read a DICOM mammogram (MG, or CR/DX "for presentation") into a canonical image.

What is read, and from where (each recorded in :attr:`MammogramImage.meta`):

* pixels: decoded by pydicom (RLE, JPEG, JPEG-LS, JPEG 2000 through the pylibjpeg
  plug-ins), then the Modality LUT/rescale and the VOI LUT or window
  (``apply_voi_lut``), inverted for ``MONOCHROME1`` and scaled to [0, 1] so that bright
  means dense;
* pixel spacing (row, col) in mm: the user's value, else ``PixelSpacing``, else
  ``ImagerPixelSpacing / EstimatedRadiographicMagnificationFactor`` (the spacing at the
  detector divided by the magnification of the breast; DICOM PS3.3 C.8.11.7), else
  ``ImagerPixelSpacing``; without any, :class:`~regtrack.errors.DicomError`;
* laterality: ``ImageLaterality``, else ``Laterality``, else the image content (the edge
  the breast rests on, under the IHE hanging: left edge = left breast);
* view: ``ViewPosition``, else ``ViewCodeSequence``, else a view code stored in
  ``PatientOrientation`` (CBIS-DDSM does this), else the image content (a pectoral muscle
  found in the top corner = MLO);
* orientation: ``PatientOrientation`` when valid, else the IHE standard hanging; the
  left-right flip is then checked against the image content (chest wall on the left).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from regtrack.errors import DicomError, MammogramError
from regtrack.views import LATERALITIES, VIEWS

from .orient import (Orientation, orientation_from_hanging, orientation_from_tag,
                     parse_patient_orientation)

log = logging.getLogger(__name__)

ACCEPTED_MODALITIES = ("MG", "DX", "CR")
_VIEW_CODES = {"CC": "CC", "XCCL": "CC", "XCCM": "CC", "FB": "CC", "MLO": "MLO"}
_VIEW_MEANINGS = {"cranio-caudal": "CC", "medio-lateral oblique": "MLO"}


@dataclass
class MammogramImage:
    """A mammogram in the canonical orientation of :mod:`regtrack.views`.

    Attributes
    ----------
    image : 2-D float32
        Values in [0, 1], bright = dense, chest wall on the left, nipple to the right.
    pixel_spacing : (2,) float
        (row, col) spacing of ``image`` in mm.
    view : {"CC", "MLO"}
    laterality : {"L", "R"}
    orientation : Orientation
        Map from the DICOM's own pixel grid to ``image``.
    source : str
        File name (or a label for arrays).
    meta : dict
        Where each fact came from (``spacing_source``, ``laterality_source``,
        ``view_source``, ``orientation``), the modality, notes on fall-backs.
    """

    image: np.ndarray
    pixel_spacing: np.ndarray
    view: str
    laterality: str
    orientation: Orientation
    source: str = ""
    meta: dict = field(default_factory=dict)

    def to_canonical_px(self, rc) -> np.ndarray:
        """Map (..., 2) (row, col) of the DICOM's own grid to (row, col) of ``image``."""
        return self.orientation.to_canonical_px(rc)

    def to_source_px(self, rc) -> np.ndarray:
        """Map (..., 2) (row, col) of ``image`` back to the DICOM's own grid."""
        return self.orientation.to_source_px(rc)


def _user_choice(value: str | None, allowed: tuple[str, ...], what: str, where: str) -> str | None:
    """The caller's view or laterality (``what``) upper-cased and checked against ``allowed``;
    None when not given (the tags and the image decide)."""
    if value is None:
        return None
    v = str(value).strip().upper()
    if v not in allowed:
        choices = " or ".join(repr(a) for a in allowed)
        raise DicomError(f"{where}: {what} {value!r} is not supported; use {choices}")
    return v


def _spacing_from_tags(ds, name: str, user) -> tuple[np.ndarray, str]:
    if user is not None:
        sp = np.asarray(user, float).reshape(-1)
        if sp.size != 2 or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
            raise DicomError(f"{name}: pixel_spacing_mm {list(user)!r} must be two positive "
                             "numbers [row, col] in mm")
        tag = ds.get("PixelSpacing") or ds.get("ImagerPixelSpacing")
        if tag is not None:
            log.warning("%s: user pixel spacing %s mm overrides the DICOM value %s", name,
                        sp.tolist(), [float(v) for v in tag])
        return sp, "user (pixel_spacing_mm)"
    if ds.get("PixelSpacing"):
        return _spacing_tag(ds, "PixelSpacing", name), "PixelSpacing"
    if ds.get("ImagerPixelSpacing"):
        sp = _spacing_tag(ds, "ImagerPixelSpacing", name)
        mag = _finite_or_none(ds.get("EstimatedRadiographicMagnificationFactor"))
        if mag is not None and mag > 0:
            return sp / float(mag), ("ImagerPixelSpacing / EstimatedRadiographicMagnification"
                                     f"Factor ({float(mag):g})")
        return sp, "ImagerPixelSpacing"
    raise DicomError(f"{name}: no PixelSpacing or ImagerPixelSpacing tag; give "
                     "pixel_spacing_mm = [row, col] (mm) under [views.<VIEW>] in case.toml "
                     "(or --spacing R C)")


def _finite_or_none(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _spacing_tag(ds, keyword: str, name: str) -> np.ndarray:
    """``(row, col)`` mm of a spacing tag; anything but two positive numbers is an error."""
    value = ds.get(keyword)
    values = [value] if isinstance(value, (str, bytes, int, float)) else list(value)
    sp = np.asarray([_finite_or_none(v) for v in values], dtype=float)
    if sp.size != 2 or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise DicomError(f"{name}: {keyword} {[str(v) for v in values]} is not two positive "
                         "numbers (row, col) in mm; fix the tag or give pixel_spacing_mm = "
                         "[row, col] under [views.<VIEW>] in case.toml (or --spacing R C)")
    return sp


def _laterality_from_tags(ds) -> tuple[str | None, str]:
    for kw in ("ImageLaterality", "Laterality"):
        v = str(ds.get(kw, "") or "").strip().upper()
        if v in LATERALITIES:
            return v, kw
    return None, ""


def _view_from_tags(ds) -> tuple[str | None, str]:
    v = str(ds.get("ViewPosition", "") or "").strip().upper()
    if v in _VIEW_CODES:
        return _VIEW_CODES[v], "ViewPosition"
    for item in ds.get("ViewCodeSequence", []) or []:
        meaning = str(item.get("CodeMeaning", "")).strip().lower()
        if meaning in _VIEW_MEANINGS:
            return _VIEW_MEANINGS[meaning], "ViewCodeSequence"
    po = ds.get("PatientOrientation")
    if po is not None:
        vals = [po] if isinstance(po, str) else list(po)
        if len(vals) == 1 and str(vals[0]).strip().upper() in _VIEW_CODES:
            return _VIEW_CODES[str(vals[0]).strip().upper()], \
                "PatientOrientation (non-standard: holds the view code)"
    return None, ""


def _pixels(ds, name: str, apply_voi: bool) -> tuple[np.ndarray, dict]:
    from pydicom.pixels import apply_modality_lut, apply_voi_lut

    from regtrack.imaging.pixel_decoding import check_pixel_header, decode_failure

    problem = check_pixel_header(ds, name)  # a corrupt size claim, before any allocation
    if problem:
        raise DicomError(problem)
    try:
        arr = ds.pixel_array
    except Exception as err:  # decoder missing or corrupt data
        raise DicomError(decode_failure(ds, name, err)) from err
    info: dict = {}
    if arr.ndim != 2:
        raise DicomError(f"{name}: pixel data has shape {arr.shape}; a single-frame grey-level "
                         "mammogram is needed (NumberOfFrames 1, SamplesPerPixel 1)")
    try:
        out = apply_modality_lut(arr, ds).astype(np.float64)
    except Exception as err:  # noqa: BLE001 - malformed RescaleSlope / Modality LUT
        raise DicomError(f"{name}: cannot apply the Modality LUT / RescaleSlope and "
                         f"RescaleIntercept ({err}); fix those tags") from err
    if not np.isfinite(out).all():
        raise DicomError(f"{name}: RescaleSlope {ds.get('RescaleSlope')} / RescaleIntercept "
                         f"{ds.get('RescaleIntercept')} give non-finite pixel values; fix those tags")
    has_voi = bool(ds.get("VOILUTSequence") or ds.get("WindowCenter") is not None)
    info["voi"] = "none"
    if apply_voi and has_voi:
        try:
            voi = np.asarray(apply_voi_lut(out, ds, index=0), dtype=np.float64)
        except Exception as err:  # noqa: BLE001 - e.g. WindowWidth 0: the tag, not the image
            info["voi_error"] = (f"{name}: VOI LUT / window not applied ({err}); the image is "
                                 "used without it")
            log.warning("%s", info["voi_error"])
        else:
            if np.isfinite(voi).all():
                out = voi
                info["voi"] = "VOILUTSequence" if ds.get("VOILUTSequence") else "WindowCenter/Width"
            else:
                info["voi_error"] = f"{name}: the VOI window gives non-finite values; not applied"
                log.warning("%s", info["voi_error"])
    lo, hi = float(out.min()), float(out.max())
    if not hi > lo:
        raise DicomError(f"{name}: pixel data are constant ({lo:g}); not an image")
    img = (out - lo) / (hi - lo)
    pi = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip().upper()
    if pi == "MONOCHROME1":
        img = 1.0 - img
    elif pi != "MONOCHROME2":
        raise DicomError(f"{name}: PhotometricInterpretation {pi} is not supported; a "
                         "grey-level mammogram (MONOCHROME1/2) is needed")
    info["photometric"] = pi
    return img.astype(np.float32), info


def read_mammogram(path: str | os.PathLike, *, pixel_spacing_mm=None, view: str | None = None,
                   laterality: str | None = None, apply_voi: bool = True) -> MammogramImage:
    """Read a DICOM mammogram into the canonical orientation.

    Parameters
    ----------
    path : path-like
        DICOM file (MG, or CR/DX for presentation).
    pixel_spacing_mm : (2,) float, optional
        (row, col) spacing in mm; required when the file has no spacing tag, and
        overrides the tags otherwise (with a warning).
    view : {"CC", "MLO"}, optional
        Overrides the tags.
    laterality : {"L", "R"}, optional
        Overrides the tags.
    apply_voi : bool
        Apply the VOI LUT / window stored in the file.

    Raises
    ------
    DicomError
        Unreadable file, wrong modality, no spacing, undecodable pixels.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise DicomError(f"{name}: file not found; check the mammogram path")
    try:
        ds = pydicom.dcmread(path)
        for _ in ds:  # pydicom decodes lazily: surface every malformed element here
            pass
    except InvalidDicomError as err:
        raise DicomError(f"{name}: not a DICOM file ({err}); give a DICOM MG/DX/CR image") from err
    except Exception as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0][:160]
        raise DicomError(f"{name}: cannot read the DICOM file ({first}); the file may be "
                         "truncated or corrupt") from err
    modality = str(ds.get("Modality", "") or "").strip().upper()
    meta: dict = {"modality": modality or None, "notes": []}
    if modality and modality not in ACCEPTED_MODALITIES:
        raise DicomError(f"{name}: Modality {modality} is not a mammogram; give a DICOM "
                         f"with Modality {', '.join(ACCEPTED_MODALITIES)}")
    if not modality:
        _note(meta, f"{name}: no Modality tag; read as a mammogram")
    if "PixelData" not in ds:
        raise DicomError(f"{name}: no PixelData; give an image, not a header-only DICOM")
    intent = str(ds.get("PresentationIntentType", "") or "").strip().upper()
    if intent == "FOR PROCESSING":
        _note(meta, f"{name}: PresentationIntentType FOR PROCESSING (raw detector data); "
                    "segmentation expects a for-presentation image")
    spacing, meta["spacing_source"] = _spacing_from_tags(ds, name, pixel_spacing_mm)
    img, pinfo = _pixels(ds, name, apply_voi)
    meta.update(pinfo)
    lat_tag, lat_src = _laterality_from_tags(ds)
    view_tag, view_src = _view_from_tags(ds)
    lat_user = _user_choice(laterality, LATERALITIES, "laterality", name)
    view_user = _user_choice(view, VIEWS, "view", name)
    return _canonicalise(
        img, spacing, name=name, meta=meta,
        laterality=(lat_user or lat_tag), laterality_source=("user" if lat_user else lat_src),
        view=(view_user or view_tag), view_source=("user" if view_user else view_src),
        patient_orientation=ds.get("PatientOrientation"))


def mammogram_from_array(image, *, pixel_spacing_mm, view: str | None = None,
                         laterality: str | None = None, patient_orientation=None,
                         source: str = "array") -> MammogramImage:
    """Build a :class:`MammogramImage` from a 2-D array stored like a DICOM grid.

    ``image`` is scaled to [0, 1] (bright = dense) and oriented with the same rules as
    :func:`read_mammogram` (``patient_orientation`` plays the tag's role).
    """
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim != 2:
        raise DicomError(f"{source}: image must be 2-D, got shape {arr.shape}")
    arr = np.nan_to_num(arr, nan=float(np.nanmin(arr)))
    lo, hi = float(arr.min()), float(arr.max())
    if not hi > lo:
        raise DicomError(f"{source}: image is constant; not a mammogram")
    if pixel_spacing_mm is None:
        raise DicomError(f"{source}: pixel_spacing_mm is required for an array")
    sp, _ = _spacing_from_tags({}, source, pixel_spacing_mm)
    meta: dict = {"modality": None, "notes": [], "spacing_source": "user (pixel_spacing_mm)"}
    lat_user = _user_choice(laterality, LATERALITIES, "laterality", source)
    view_user = _user_choice(view, VIEWS, "view", source)
    return _canonicalise(((arr - lo) / (hi - lo)).astype(np.float32), sp, name=source, meta=meta,
                         laterality=lat_user, laterality_source="user" if lat_user else "",
                         view=view_user, view_source="user" if view_user else "",
                         patient_orientation=patient_orientation)


def _note(meta: dict, msg: str) -> None:
    log.warning(msg)
    meta["notes"].append(msg)


def _canonicalise(img: np.ndarray, spacing: np.ndarray, *, name: str, meta: dict,
                  laterality: str | None, laterality_source: str, view: str | None,
                  view_source: str, patient_orientation) -> MammogramImage:
    """Decide laterality, view and flips (tags first, image content as fall-back)."""
    from .segment import chest_wall_side

    try:
        side, side_conf = chest_wall_side(img, spacing)
    except MammogramError as err:
        raise MammogramError(f"{name}: {str(err).removeprefix('mammogram: ')}") from err
    meta["chest_wall_side_in_file"] = {"side": side, "confidence": round(side_conf, 3)}
    if laterality is None:
        laterality = "L" if side == "left" else "R"
        laterality_source = (f"image content (chest wall on the {side} edge => {laterality} "
                             "under the IHE hanging)")
        _note(meta, f"{name}: no ImageLaterality/Laterality tag; laterality {laterality} "
                    f"from the image content (confidence {side_conf:.2f}); give laterality "
                    "to override")
    po = parse_patient_orientation(patient_orientation)
    if view is None:
        view, view_source = _view_from_content(img[:, ::-1] if side == "right" else img, spacing)
        _note(meta, f"{name}: no ViewPosition tag; view {view} from the image content; give "
                    "view to override")
    if po is not None:
        orient, notes = orientation_from_tag(po, shape=img.shape, view=view, laterality=laterality)
        for n in notes:
            _note(meta, f"{name}: {n}")
    else:
        if patient_orientation is not None and str(patient_orientation).strip():
            meta["notes"].append(f"PatientOrientation {str(patient_orientation)!r} is not a "
                                 "valid orientation; IHE standard hanging assumed")
        orient = orientation_from_hanging(shape=img.shape, laterality=laterality, view=view)
    # check the left-right flip against the content: the chest wall must end on the left
    if not orient.transpose and side_conf > 0.2:
        want_flip = side == "right"
        if want_flip != orient.flip_lr:
            _note(meta, f"{name}: {orient.rule} puts the chest wall on the right, but the "
                        f"breast rests on the {side} edge of the stored image; flipped "
                        "left-right from the image content")
            orient = orient.with_flip_lr(want_flip,
                                         orient.rule + " + left-right flip from image content")
    sp = spacing[::-1].copy() if orient.transpose else spacing.copy()
    if view == "MLO" and po is None:
        # without a usable PatientOrientation, check the vertical axis on the content:
        # the pectoral muscle belongs in the top-left corner of the canonical MLO
        canon = orient.apply(img)
        top, bottom = _pectoral_contrast(canon, sp), _pectoral_contrast(canon[::-1], sp)
        meta["pectoral_contrast_top_bottom"] = [top, bottom]
        if bottom > 0 and bottom > 1.5 * top:
            _note(meta, f"{name}: the pectoral muscle is in the bottom corner (contrast "
                        f"{bottom:.2f} vs {top:.2f} at the top); flipped up-down from the "
                        "image content")
            orient = orient.with_flip_ud(not orient.flip_ud,
                                         orient.rule + " + up-down flip from image content")
    canon = orient.apply(img)
    meta["laterality_source"] = laterality_source
    meta["view_source"] = view_source
    meta["orientation"] = {"rule": orient.rule, "transpose": orient.transpose,
                           "flip_lr": orient.flip_lr, "flip_ud": orient.flip_ud,
                           "source_shape": list(orient.source_shape)}
    meta["spacing_mm"] = [float(v) for v in sp]
    log.info("%s: %s%s, %dx%d px at %.4gx%.4g mm (%s), %s", name, laterality, view,
             canon.shape[0], canon.shape[1], sp[0], sp[1], meta["spacing_source"], orient.rule)
    return MammogramImage(image=canon, pixel_spacing=sp, view=view, laterality=laterality,
                          orientation=orient, source=name, meta=meta)


def _pectoral_contrast(canon: np.ndarray, spacing: np.ndarray) -> float:
    """Contrast of the pectoral muscle found in the top-left corner (0 when none)."""
    from .config import MammogramConfig
    from .segment import segment_breast

    seg = segment_breast(canon, spacing, view="MLO", config=MammogramConfig(working_spacing_mm=1.0))
    return 0.0 if seg.pectoral is None else float(seg.pectoral["contrast"])


def _view_from_content(img: np.ndarray, spacing: np.ndarray) -> tuple[str, str]:
    """MLO when a pectoral muscle is found in a chest-wall corner, else CC.

    ``img`` has the chest wall on the left; both the top-left and the bottom-left corner
    are searched (the vertical orientation is not known yet).
    """
    c = max(_pectoral_contrast(img, spacing), _pectoral_contrast(img[::-1], spacing))
    if c > 0:
        return "MLO", f"image content (pectoral muscle found, contrast {c:.3f})"
    return "CC", "image content (no pectoral muscle in a chest-wall corner)"
