"""Read and write label maps and MRI volumes with their real-world (LPS, mm) geometry.

Formats
-------
* NIfTI (``.nii``, ``.nii.gz``), MetaImage (``.mha``, ``.mhd`` + raw), NRRD (``.nrrd``,
  ``.nhdr``): read with SimpleITK, whose origin / spacing / direction are already in the
  ITK LPS convention, so ``affine = make_affine(origin, spacing, direction)`` and
  ``data = GetArrayFromImage(img).transpose(2, 1, 0)`` (numpy axis 0 = ITK index ``i``).
* ``.zip`` holding one MetaImage (``.mha``, or ``.mhd`` with its raw file) or one NIfTI/NRRD,
  as the Pelicano label maps are distributed: extracted to a temporary folder and read as
  above (an 80 MB float32 MHA takes well under a second).
* a folder: a DICOM series, one file per slice (:mod:`regtrack.imaging.dicom_series`).

MetaIO note (checked against SimpleITK on the Pelicano exams in ``tests/test_readers.py``):
``TransformMatrix = m0 ... m8`` is stored column by column, i.e. the LPS direction of
array axis ``a`` is ``(m[3a], m[3a+1], m[3a+2])``; SimpleITK's row-major
``GetDirection()`` is therefore the *transpose* of the header read row-major.
``Offset`` is the LPS centre of voxel (0, 0, 0) and ``ElementSpacing`` the voxel size.
``AnatomicalOrientation`` is informational and ignored (by ITK too).
"""

from __future__ import annotations

import logging
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from regtrack._io import atomic_path
from regtrack.errors import InputFileError
from regtrack.imaging.dicom_series import read_dicom_series, write_dicom_series
from regtrack.imaging.volume import ImageVolume, LabelVolume, Volume, make_affine

log = logging.getLogger(__name__)

_ITK_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
_WRITE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".nrrd")


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for s in (".nii.gz", *_ITK_SUFFIXES, ".zip"):
        if name.endswith(s):
            return s
    return path.suffix.lower()


def _check_nifti_complete(path: Path) -> None:
    """Refuse a NIfTI file shorter than its header says, or a broken gzip stream.

    ITK reads a truncated ``.nii.gz`` silently and zero-fills the missing voxels (a 7.3 mL
    tumour became 1.9 mL at 80 % of the file, issue 53), so the voxel bytes are counted
    here: the (decompressed) file must hold ``vox_offset + prod(dim) * bitpix / 8`` bytes,
    and a ``.nii.gz`` must end with its gzip end-of-stream marker and a matching CRC.
    """
    import gzip
    import zlib

    import nibabel

    have: int | None = None
    with open(path, "rb") as f:
        gzipped = f.read(2) == b"\x1f\x8b"  # else not gzip at all: ITK's error says so
    if _suffix(path) == ".nii.gz" and gzipped:  # the stream first: a cut may hit the header
        have = 0
        try:
            with gzip.open(path, "rb") as f:
                while chunk := f.read(1 << 20):
                    have += len(chunk)
        except (EOFError, OSError, zlib.error) as exc:
            raise InputFileError(
                f"{path}: the gzip stream is truncated or corrupt ({exc}); the file is "
                "incomplete: copy or export it again"
            ) from None
    try:
        proxy = nibabel.load(str(path)).dataobj  # reads the header only
        shape, dtype = tuple(proxy.shape), np.dtype(proxy.dtype)
        need = int(proxy.offset) + int(np.prod(shape)) * dtype.itemsize
    except Exception as exc:  # noqa: BLE001 - nibabel's many header errors: ITK says more
        log.debug("%s: nibabel cannot read the header (%s); left to ITK", path, exc)
        return
    if have is None:
        have = path.stat().st_size
    if have < need:
        raise InputFileError(
            f"{path}: the file holds {have} bytes but its header ({'x'.join(map(str, shape))} "
            f"voxels of {dtype}) needs {need}; the file is truncated: copy "
            "or export it again"
        )


def _read_itk(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(data, affine)`` of a NIfTI / MetaImage / NRRD file via SimpleITK."""
    import SimpleITK as sitk

    if _suffix(path) in (".nii", ".nii.gz"):
        _check_nifti_complete(path)
    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        hint = next((ln for ln in first if "ERROR" in ln or "rror" in ln), first[-1] if first else "")
        raise InputFileError(
            f"{path}: cannot read the image ({hint.strip()[:200]}); check that the file is a "
            "complete NIfTI/MetaImage/NRRD file"
        ) from exc
    if img.GetDimension() != 3:
        raise InputFileError(
            f"{path}: image has {img.GetDimension()} dimensions; a 3-D volume is required"
        )
    if img.GetNumberOfComponentsPerPixel() != 1:
        raise InputFileError(
            f"{path}: image has {img.GetNumberOfComponentsPerPixel()} components per voxel; "
            "a scalar volume is required"
        )
    data = sitk.GetArrayFromImage(img).transpose(2, 1, 0)
    if _suffix(path) in (".nii", ".nii.gz") and np.issubdtype(data.dtype, np.floating):
        data = _restore_nifti_nan(path, data)
    direction = np.asarray(img.GetDirection(), float).reshape(3, 3)
    affine = make_affine(img.GetOrigin(), img.GetSpacing(), direction)
    return data, affine


def _restore_nifti_nan(path: Path, data: np.ndarray) -> np.ndarray:
    """ITK's NIfTI reader silently turns NaN voxels into 0 (measured with SimpleITK 2.x);
    put them back from the raw voxels (nibabel) so the label checks can refuse them."""
    try:
        import nibabel
    except ImportError:  # pragma: no cover - nibabel ships with the test environment
        log.warning("%s: nibabel not installed; NaN voxels of a float NIfTI read as 0", path.name)
        return data
    raw = np.asanyarray(nibabel.load(str(path)).dataobj)
    bad = ~np.isfinite(raw)
    if raw.shape[:3] != data.shape[:3] or not bad.any():
        return data
    out = data.astype(np.float64)
    out[bad.reshape(out.shape)] = np.nan
    return out


def _read_zip(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Extract the one image of a zip archive to a temporary folder and read it."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise InputFileError(f"{path}: not a readable zip archive ({exc})") from exc
    with zf:
        members = [m for m in zf.infolist() if not m.is_dir() and not Path(m.filename).name.startswith(".")
                   and "__MACOSX" not in m.filename]
        images = [m for m in members if _suffix(Path(m.filename)) in _ITK_SUFFIXES]
        if len(images) != 1:
            names = ", ".join(m.filename for m in members) or "nothing"
            raise InputFileError(
                f"{path}: expected exactly one image (.mha/.mhd/.nii/.nii.gz/.nrrd) in the zip, "
                f"found {len(images)} (members: {names}); zip a single volume"
            )
        with tempfile.TemporaryDirectory(prefix="regtrack-zip-") as tmp:
            # flatten member paths (no traversal outside tmp); keep names so .mhd finds its raw
            for m in members:
                target = Path(tmp) / Path(m.filename).name
                with zf.open(m) as src, open(target, "wb") as dst:
                    while chunk := src.read(1 << 24):
                        dst.write(chunk)
            try:
                return _read_itk(Path(tmp) / Path(images[0].filename).name)
            except InputFileError as exc:
                raise InputFileError(f"{path} (member {images[0].filename}): {exc}") from exc


def _read_any(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, Path, dict]:
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: file not found (check the path in case.toml)")
    if path.is_dir():
        data, affine, meta = read_dicom_series(path)
        return data, affine, path, {"format": "dicom", **meta}
    sfx = _suffix(path)
    if sfx == ".zip":
        data, affine = _read_zip(path)
        return data, affine, path, {"format": "zip"}
    if sfx in _ITK_SUFFIXES:
        data, affine = _read_itk(path)
        return data, affine, path, {"format": sfx.lstrip(".")}
    raise InputFileError(
        f"{path}: unknown volume format '{sfx}'; use NIfTI (.nii/.nii.gz), MetaImage "
        "(.mha/.mhd), NRRD (.nrrd), a .zip holding one .mha, or a DICOM series folder"
    )


def to_labels(data: np.ndarray, *, path: Path | str, label_dtype=np.int16) -> np.ndarray:
    """Convert label data to ``label_dtype``; refuse NaN, non-integral or out-of-range values.

    ``path`` is only used in the error message.
    """
    data = np.asarray(data)
    dt = np.dtype(label_dtype)
    if np.issubdtype(data.dtype, np.floating):
        finite = np.isfinite(data)
        if not finite.all():
            n = int((~finite).sum())
            raise InputFileError(
                f"{path}: labels contain {n} NaN/inf voxels; fix the label map (every voxel "
                "needs an integer label, 0 for background)"
            )
        frac = np.abs(data - np.round(data))
        if frac.max() > 1e-4:
            idx = np.unravel_index(int(np.argmax(frac)), data.shape)
            raise InputFileError(
                f"{path}: labels are not integers (e.g. {float(data[idx])!r} at voxel {list(idx)}); "
                "this looks like an intensity image or a resampled label map: use nearest-"
                "neighbour interpolation or pass the label map, not the MRI"
            )
        data = np.round(data)
    elif not np.issubdtype(data.dtype, np.integer) and data.dtype != bool:
        raise InputFileError(f"{path}: voxel type {data.dtype} cannot hold labels")
    info = np.iinfo(dt)
    lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
    if lo < info.min or hi > info.max:
        raise InputFileError(
            f"{path}: label values span [{lo}, {hi}], outside {dt.name}; pass a wider label_dtype"
        )
    return data.astype(dt)


def read_label_map(path: str | os.PathLike, *, label_dtype=np.int16) -> LabelVolume:
    """Read a label map (NIfTI, MHA/MHD, NRRD, zipped MHA or DICOM folder).

    Parameters
    ----------
    path
        File or DICOM series folder.
    label_dtype
        Integer dtype of the returned labels.

    Returns
    -------
    LabelVolume
        ``data[i, j, k]`` integer labels; ``affine`` maps ``(i, j, k, 1)`` to LPS (mm).

    Raises
    ------
    InputFileError
        Missing/unreadable file, unknown format, NaN or non-integral labels (the message
        names the file).
    """
    data, affine, src, meta = _read_any(path)
    labels = to_labels(data, path=src, label_dtype=label_dtype)
    meta["source_dtype"] = str(data.dtype)
    log.info("label map %s: shape %s, spacing %s mm", src, labels.shape,
             np.round(np.linalg.norm(affine[:3, :3], axis=0), 4).tolist())
    return LabelVolume(labels, affine, src, meta)


def read_image_volume(path: str | os.PathLike, *, series_uid: str | None = None) -> ImageVolume:
    """Read an intensity volume (same formats as :func:`read_label_map`, or a DICOM MR series).

    Returns float32 data (DICOM RescaleSlope/Intercept applied) with the LPS affine.
    ``series_uid`` selects one series in a DICOM folder holding several.
    """
    p = Path(path)
    if p.is_dir():
        data, affine, meta = read_dicom_series(p, series_uid=series_uid)
        meta = {"format": "dicom", **meta}
    else:
        data, affine, p, meta = _read_any(p)
    if not np.issubdtype(np.asarray(data).dtype, np.number):
        raise InputFileError(f"{p}: voxel type {data.dtype} is not numeric")
    return ImageVolume(np.asarray(data, dtype=np.float32), affine, p, meta)


def _smallest_int_dtype(data: np.ndarray, path: Path) -> np.dtype:
    lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
    for dt in (np.int8, np.uint8, np.int16, np.uint16, np.int32):
        info = np.iinfo(dt)
        if info.min <= lo and hi <= info.max:
            return np.dtype(dt)
    raise InputFileError(f"{path}: label values span [{lo}, {hi}], too wide for int32")


def _to_itk(vol: Volume, data: np.ndarray):
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(np.ascontiguousarray(data.transpose(2, 1, 0)))
    img.SetOrigin(tuple(float(v) for v in vol.origin))
    img.SetSpacing(tuple(float(v) for v in vol.spacing))
    img.SetDirection(tuple(float(v) for v in vol.direction.ravel()))
    return img


def _write_itk(vol: Volume, data: np.ndarray, path: Path) -> Path:
    import SimpleITK as sitk

    sfx = _suffix(path)
    if sfx not in _WRITE_SUFFIXES:
        raise InputFileError(
            f"{path}: cannot write format '{sfx}'; use .nii.gz, .nii, .mha or .nrrd "
            "(.mhd would need a separate raw file)"
        )
    img = _to_itk(vol, data)
    with atomic_path(path, suffix=sfx) as tmp:
        sitk.WriteImage(img, str(tmp), useCompression=sfx != ".nii")
    return path


def write_label_map(vol: LabelVolume, path: str | os.PathLike) -> Path:
    """Write a label map, compressed, in the format named by the extension.

    ``.nii.gz`` (gzip), ``.mha`` / ``.nrrd`` (zlib-compressed data) or ``.nii``.  The voxel
    type is the smallest integer type holding the labels (int8 for Pelicano-style maps).
    Written atomically; the affine survives a round trip through :func:`read_label_map`.
    """
    path = Path(path)
    data = to_labels(vol.data, path=path, label_dtype=np.int64)
    data = data.astype(_smallest_int_dtype(data, path))
    return _write_itk(vol, data, path)


def write_image_volume(vol: ImageVolume, path: str | os.PathLike) -> Path:
    """Write an intensity volume as float32 (compressed ``.nii.gz`` / ``.mha`` / ``.nrrd``)."""
    path = Path(path)
    return _write_itk(vol, np.asarray(vol.data, dtype=np.float32), path)


__all__ = [
    "read_label_map",
    "read_image_volume",
    "write_label_map",
    "write_image_volume",
    "write_dicom_series",
    "to_labels",
    "read_dicom_series",
]
