"""DICOM series (one file per slice) <-> 3-D volume with a voxel-to-LPS affine.

Geometry (DICOM PS3.3 C.7.6.2.1.1).  For slice ``k`` with ImagePositionPatient ``p_k``,
ImageOrientationPatient ``(r, c)`` (``r``: LPS direction of increasing *column* index,
``c``: of increasing *row* index) and PixelSpacing ``(Δrow, Δcol)`` the LPS position (mm)
of pixel ``(row, col)`` is::

    x = p_k + col * Δcol * r + row * Δrow * c

The volume is stored as ``data[i, j, k] = pixel[row=j, col=i]`` of slice ``k`` (the
ITK/SimpleITK index order), so the affine is::

    A[:3, 0] = Δcol * r,   A[:3, 1] = Δrow * c,   A[:3, 2] = (p_{n-1} - p_0) / (n - 1),
    A[:3, 3] = p_0

with the slices sorted by their position along the normal ``n = r x c``.
"""

from __future__ import annotations

import datetime
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from regtrack._io import atomic_path
from regtrack.errors import DicomError, InputFileError
from regtrack.imaging.pixel_decoding import check_pixel_header, decode_failure

log = logging.getLogger(__name__)

MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4"
#: tolerance (mm) on slice positions and in-plane offsets of a series
POSITION_TOL_MM = 0.01
#: tolerance on direction cosines (orientation equality, orthogonality)
DIRECTION_TOL = 1e-4

#: attributes a derived series copies from its source (``write_dicom_series(template=)``):
#: the patient and general-study modules, the frame of reference, and the patient position
FROM_SOURCE = (
    "PatientName", "PatientID", "PatientBirthDate", "PatientSex", "PatientAge",
    "PatientWeight", "PatientSize", "StudyInstanceUID", "StudyDate", "StudyTime", "StudyID",
    "AccessionNumber", "ReferringPhysicianName", "StudyDescription", "FrameOfReferenceUID",
    "PositionReferenceIndicator", "PatientPosition", "BodyPartExamined",
)

TRANSFER_SYNTAXES = {
    "jpeg2000": "1.2.840.10008.1.2.4.90",  # JPEG 2000 Image Compression (Lossless Only)
    "rle": "1.2.840.10008.1.2.5",  # RLE Lossless
    "explicit": "1.2.840.10008.1.2.1",  # Explicit VR Little Endian (uncompressed)
}


@dataclass(frozen=True)
class _SliceHeader:
    path: Path
    position: np.ndarray  # ImagePositionPatient (mm)
    orientation: np.ndarray  # ImageOrientationPatient (6,)
    spacing: tuple[float, float]  # PixelSpacing (row, col) mm
    shape: tuple[int, int]  # (Rows, Columns)
    series_uid: str


def _tag(ds, name: str, path: Path):
    value = getattr(ds, name, None)
    if value is None or (hasattr(value, "__len__") and len(value) == 0):
        raise DicomError(
            f"{path}: DICOM tag {name} is missing; regtrack needs it to place the slice in "
            "patient space (re-export the series with full geometry)"
        )
    return value


def _read_header(path: Path) -> _SliceHeader | None:
    import pydicom
    from pydicom.errors import InvalidDicomError

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except (InvalidDicomError, OSError, EOFError, ValueError, TypeError):
        log.debug("skipping %s: not a DICOM file", path)
        return None
    if "PixelData" not in ds and not hasattr(ds, "Rows"):
        log.debug("skipping %s: DICOM without pixel data", path)
        return None
    if int(getattr(ds, "NumberOfFrames", 1) or 1) > 1:
        raise DicomError(
            f"{path}: NumberOfFrames = {ds.NumberOfFrames}: enhanced multi-frame DICOM is not "
            "supported; export the series as classic single-frame images (one file per slice)"
        )
    return _SliceHeader(
        path=path,
        position=np.asarray(_tag(ds, "ImagePositionPatient", path), float),
        orientation=np.asarray(_tag(ds, "ImageOrientationPatient", path), float),
        spacing=tuple(float(v) for v in _tag(ds, "PixelSpacing", path)),  # type: ignore[arg-type]
        shape=(int(_tag(ds, "Rows", path)), int(_tag(ds, "Columns", path))),
        series_uid=str(getattr(ds, "SeriesInstanceUID", "")),
    )


def _list_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))


def _select_series(headers: list[_SliceHeader], folder: Path, series_uid: str | None):
    uids = sorted({h.series_uid for h in headers})
    if series_uid is not None:
        headers = [h for h in headers if h.series_uid == series_uid]
        if not headers:
            raise InputFileError(
                f"{folder}: no slice with SeriesInstanceUID {series_uid}; series present: "
                + ", ".join(uids)
            )
    elif len(uids) > 1:
        raise InputFileError(
            f"{folder}: {len(uids)} DICOM series in one folder (SeriesInstanceUID "
            + ", ".join(uids)
            + "); put each series in its own folder or pass series_uid="
        )
    return headers


def _check_consistent(headers: list[_SliceHeader], folder: Path) -> None:
    ref = headers[0]
    for h in headers[1:]:
        if not np.allclose(h.orientation, ref.orientation, atol=DIRECTION_TOL):
            raise InputFileError(
                f"{h.path}: ImageOrientationPatient {list(h.orientation)} differs from "
                f"{ref.path.name} {list(ref.orientation)}; a series must have one orientation "
                f"(remove stray files from {folder})"
            )
        if not np.allclose(h.spacing, ref.spacing, rtol=1e-5, atol=1e-6):
            raise InputFileError(
                f"{h.path}: PixelSpacing {h.spacing} differs from {ref.path.name} {ref.spacing}; "
                f"a series must have one pixel spacing (remove stray files from {folder})"
            )
        if h.shape != ref.shape:
            raise InputFileError(
                f"{h.path}: Rows/Columns {h.shape} differ from {ref.path.name} {ref.shape}; "
                f"a series must have one image size (remove stray files from {folder})"
            )
    r, c = ref.orientation[:3], ref.orientation[3:]
    if abs(np.linalg.norm(r) - 1) > 1e-3 or abs(np.linalg.norm(c) - 1) > 1e-3 or abs(r @ c) > 1e-3:
        raise InputFileError(
            f"{ref.path}: ImageOrientationPatient {list(ref.orientation)} is not two orthonormal "
            "direction cosines; the file's geometry is corrupt"
        )


def _slice_step(headers: list[_SliceHeader], normal: np.ndarray, folder: Path) -> np.ndarray:
    """Slice step vector (mm); checks uniform, unique positions on one straight line."""
    p = np.array([h.position for h in headers])
    if len(headers) == 1:
        return normal * 1.0  # refined by the caller from SliceThickness
    d = np.diff(p @ normal)
    if np.any(d < POSITION_TOL_MM):
        k = int(np.argmin(d))
        raise InputFileError(
            f"{headers[k + 1].path}: same ImagePositionPatient as {headers[k].path.name}; duplicate "
            f"slices in {folder} (keep one acquisition per folder)"
        )
    step = (p[-1] - p[0]) / (len(p) - 1)
    expected = p[0] + np.arange(len(p))[:, None] * step
    err = np.linalg.norm(p - expected, axis=1)
    if err.max() > POSITION_TOL_MM + 1e-3 * np.linalg.norm(step) * len(p):
        k = int(np.argmax(err))
        raise InputFileError(
            f"{headers[k].path}: ImagePositionPatient is {err[k]:.3f} mm off a uniform slice "
            f"stack (step {np.linalg.norm(step):.4f} mm); missing or unevenly spaced slices in "
            f"{folder}: resample the series to uniform spacing"
        )
    return step


def read_dicom_series(
    folder: str | os.PathLike, *, series_uid: str | None = None
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read a single-frame DICOM series into ``(data, affine, meta)``.

    Parameters
    ----------
    folder
        Folder holding one file per slice (non-DICOM files are ignored).
    series_uid
        Pick one SeriesInstanceUID when the folder holds several.

    Returns
    -------
    data : ndarray (ni, nj, nk) float64
        Modality values (RescaleSlope/Intercept applied), ``data[i, j, k]`` = column ``i``,
        row ``j`` of slice ``k``.
    affine : ndarray (4, 4)
        Voxel index -> LPS (mm), see the module docstring.
    meta : dict
        ``files`` (sorted), ``series_uid``, ``modality``, ``slice_thickness_mm``.

    Raises
    ------
    InputFileError
        Missing folder/slices, inconsistent orientation, spacing or size, duplicate or
        uneven slice positions.  The message names the offending file.
    """
    import pydicom

    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(f"{folder}: DICOM series folder not found")
    headers = [h for h in (_read_header(p) for p in _list_files(folder)) if h is not None]
    if not headers:
        raise InputFileError(f"{folder}: no DICOM image files found (expected one file per slice)")
    headers = _select_series(headers, folder, series_uid)
    _check_consistent(headers, folder)
    r, c = headers[0].orientation[:3], headers[0].orientation[3:]
    normal = np.cross(r, c)
    headers.sort(key=lambda h: float(h.position @ normal))
    step = _slice_step(headers, normal, folder)

    slices = []
    meta: dict = {}
    for h in headers:
        ds = pydicom.dcmread(h.path)
        problem = check_pixel_header(ds, str(h.path))
        if problem:
            raise DicomError(problem)
        try:
            arr = ds.pixel_array
        except Exception as exc:  # decoder missing / corrupt pixel data
            raise DicomError(decode_failure(ds, str(h.path), exc)) from exc
        slope = float(getattr(ds, "RescaleSlope", 1.0) or 1.0)
        intercept = float(getattr(ds, "RescaleIntercept", 0.0) or 0.0)
        slices.append(arr.T.astype(np.float64) * slope + intercept)
        if not meta:
            meta = {
                "modality": str(getattr(ds, "Modality", "")),
                "slice_thickness_mm": float(getattr(ds, "SliceThickness", 0.0) or 0.0),
                "series_description": str(getattr(ds, "SeriesDescription", "")),
            }
    if len(headers) == 1:
        thick = meta["slice_thickness_mm"] or 1.0
        step = normal * thick
    data = np.stack(slices, axis=2)
    dcol, drow = headers[0].spacing[1], headers[0].spacing[0]
    affine = np.eye(4)
    affine[:3, 0] = r * dcol
    affine[:3, 1] = c * drow
    affine[:3, 2] = step
    affine[:3, 3] = headers[0].position
    meta.update(files=[h.path for h in headers], series_uid=headers[0].series_uid)
    log.info("read DICOM series %s: %d slices, %s voxels", folder, len(headers), data.shape)
    return data, affine, meta


# ----------------------------------------------------------------------------- writer


def _stored_values(data: np.ndarray, path: Path) -> tuple[np.ndarray, float, float, bool]:
    """Map ``data`` to 16-bit stored values: ``(stored, slope, intercept, signed)``."""
    if not np.all(np.isfinite(data)):
        raise InputFileError(f"{path}: volume holds NaN/inf; cannot write it as DICOM")
    lo, hi = float(data.min()), float(data.max())
    integral = np.array_equal(data, np.round(data))
    if integral and 0 <= lo and hi <= 65535:
        return data.astype(np.uint16), 1.0, 0.0, False
    if integral and -32768 <= lo and hi <= 32767:
        return data.astype(np.int16), 1.0, 0.0, True
    slope = (hi - lo) / 65535.0 if hi > lo else 1.0
    stored = np.round((data - lo) / slope).astype(np.uint16)
    return stored, slope, lo, False


def _check_writable_geometry(affine: np.ndarray, folder: Path) -> tuple[np.ndarray, ...]:
    cols = affine[:3, :3]
    sp = np.linalg.norm(cols, axis=0)
    if np.any(sp <= 0):
        raise InputFileError(f"{folder}: volume affine has a zero voxel size; cannot write DICOM")
    r, c, s = (cols[:, a] / sp[a] for a in range(3))
    normal = np.cross(r, c)
    if abs(r @ c) > DIRECTION_TOL or abs(s @ normal - 1.0) > DIRECTION_TOL:
        raise InputFileError(
            f"{folder}: volume axes are not orthogonal with the slice axis along +(row x column); "
            "DICOM slices cannot express that geometry (resample the volume first)"
        )
    return r, c, sp


def _uid(seed: str | None, *parts: object) -> str:
    from pydicom.uid import generate_uid

    if seed is None:
        return generate_uid()
    return generate_uid(entropy_srcs=[seed, *map(str, parts)])


def write_dicom_series(
    vol,
    folder: str | os.PathLike,
    *,
    patient: str = "ANONYMOUS",
    series_description: str = "regtrack volume",
    modality: str = "MR",
    transfer_syntax: str = "jpeg2000",
    uid_seed: str | None = None,
    study_date: datetime.date | None = None,
    progress: bool = False,
    template=None,
    deidentify: bool = True,
) -> list[Path]:
    """Write ``vol`` as an MR Image Storage series, one file per slice along axis 2.

    Parameters
    ----------
    vol
        :class:`~regtrack.imaging.volume.Volume`; its axes must be orthogonal with axis 2
        along ``+(axis0 x axis1)`` (what a slice stack can express).
    folder
        Output folder (created); files are ``slice_0000.dcm``, ... written atomically.
    patient
        PatientName and PatientID (use a pseudonym).
    transfer_syntax
        ``"jpeg2000"`` (lossless, smallest), ``"rle"`` (RLE Lossless) or ``"explicit"``
        (uncompressed).
    uid_seed
        When given, every UID is derived from it, so the files are reproducible byte for byte.
    progress
        Show a progress bar.
    template
        A header (``pydicom.Dataset``) of the series this one derives from: its patient,
        study and frame-of-reference attributes (:data:`FROM_SOURCE`: StudyInstanceUID,
        FrameOfReferenceUID, ...) are copied, so the new series (new SeriesInstanceUID and
        SOPInstanceUIDs) lies in the source's study and frame of reference, numbered
        the source's SeriesNumber + 1000.
    deidentify
        Apply the PS3.15 basic profile with ``patient`` as the pseudonym
        (:func:`regtrack.privacy.deidentify_dataset`; the UIDs are kept).  ``False`` keeps
        the template's identifiers (``--keep-identifiers``).

    Notes
    -----
    Integral data in [0, 65535] (or [-32768, 32767]) is stored as is; other data is mapped
    linearly to uint16 with RescaleSlope/RescaleIntercept (error <= slope / 2).
    ImagePositionPatient of slice ``k`` is ``affine @ [0, 0, k, 1]``.
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import UID, ExplicitVRLittleEndian

    folder = Path(folder)
    if transfer_syntax not in TRANSFER_SYNTAXES:
        raise ValueError(f"transfer_syntax must be one of {sorted(TRANSFER_SYNTAXES)}, got {transfer_syntax!r}")
    affine = np.asarray(vol.affine, float)
    r, c, sp = _check_writable_geometry(affine, folder)
    stored, slope, intercept, signed = _stored_values(np.asarray(vol.data), folder)
    if transfer_syntax == "jpeg2000" and min(stored.shape[:2]) < 32:
        raise InputFileError(
            f"{folder}: slices of {stored.shape[1]}x{stored.shape[0]} pixels are too small for "
            "the JPEG 2000 encoder (6 wavelet levels need >= 32 px); use transfer_syntax='rle'"
        )
    date = (study_date or datetime.date(2000, 1, 1)).strftime("%Y%m%d")
    from regtrack.privacy import deidentify_dataset

    study_uid, series_uid, for_uid = (_uid(uid_seed, t) for t in ("study", "series", "for"))
    source = {kw: template[kw].value for kw in FROM_SOURCE
              if template is not None and kw in template}
    # a series derived in the source's study is numbered apart from it (source + 1000)
    series_number = int(template.SeriesNumber) + 1000 if "SeriesNumber" in (template or {}) else 1
    folder.mkdir(parents=True, exist_ok=True)
    nk = stored.shape[2]
    ts = UID(TRANSFER_SYNTAXES[transfer_syntax])
    normal = np.cross(r, c)
    written: list[Path] = []
    for k in _progress(range(nk), progress, f"writing {folder.name}"):
        ds = Dataset()
        sop_uid = _uid(uid_seed, "sop", k)
        ds.SOPClassUID = MR_IMAGE_STORAGE
        ds.SOPInstanceUID = sop_uid
        ds.Modality = modality
        ds.PatientName = patient
        ds.PatientID = patient
        ds.PatientBirthDate = ""
        ds.PatientSex = "F"
        ds.PatientPosition = "HFP"  # head first prone
        ds.BodyPartExamined = "BREAST"
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study_uid, series_uid, for_uid
        ds.StudyDate = ds.SeriesDate = ds.ContentDate = date
        ds.StudyTime = ds.SeriesTime = ds.ContentTime = "120000"
        ds.StudyID, ds.AccessionNumber, ds.ReferringPhysicianName = "1", "", ""
        ds.SeriesNumber, ds.InstanceNumber = series_number, k + 1
        ds.SeriesDescription = series_description
        ds.Manufacturer = "regtrack"
        ds.ScanningSequence, ds.SequenceVariant, ds.ScanOptions = "GR", "SP", ""
        ds.MRAcquisitionType = "3D"
        ds.ImageType = ["DERIVED", "SECONDARY"]
        ds.ImagePositionPatient = [float(v) for v in affine[:3, :3] @ [0, 0, k] + affine[:3, 3]]
        ds.ImageOrientationPatient = [float(v) for v in (*r, *c)]
        ds.PixelSpacing = [float(sp[1]), float(sp[0])]
        ds.SliceThickness = ds.SpacingBetweenSlices = float(sp[2])
        ds.SliceLocation = float(np.asarray(ds.ImagePositionPatient) @ normal)
        ds.PositionReferenceIndicator = ""
        ds.RescaleSlope, ds.RescaleIntercept, ds.RescaleType = slope, intercept, "US"
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.Rows, ds.Columns = stored.shape[1], stored.shape[0]
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
        ds.PixelRepresentation = 1 if signed else 0
        for kw, value in source.items():
            setattr(ds, kw, value)
        arr = np.ascontiguousarray(stored[:, :, k].T)
        ds.file_meta = FileMetaDataset()
        ds.file_meta.MediaStorageSOPClassUID = MR_IMAGE_STORAGE
        ds.file_meta.MediaStorageSOPInstanceUID = sop_uid
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds.PixelData = arr.tobytes()
        if ts != ExplicitVRLittleEndian:
            ds.compress(ts, arr, generate_instance_uid=False)
        if deidentify:
            deidentify_dataset(ds, pseudonym=patient)  # DICOM PS3.15 basic profile
        path = folder / f"slice_{k:04d}.dcm"
        with atomic_path(path) as tmp:
            ds.save_as(tmp, enforce_file_format=True)
        written.append(path)
    log.info("wrote DICOM series %s: %d slices (%s)", folder, nk, transfer_syntax)
    return written


def _progress(items: Iterable, show: bool, what: str) -> Iterable:
    if not show:
        return items
    from rich.progress import track

    return track(items, description=what, transient=True)
