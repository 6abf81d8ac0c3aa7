"""Write a simulated mammogram as a DICOM *Digital Mammography X-Ray Image - For
Presentation* object (SOP class 1.2.840.10008.5.1.4.1.1.1.2), stored the way a scanner
stores it.

Geometry tags (DICOM PS3.3 C.8.11.7 and the IHE Mammography profile):

* ``ImageLaterality`` R/L, ``ViewPosition`` CC/MLO and a ``ViewCodeSequence`` (SNOMED
  R-10242 cranio-caudal / R-10226 medio-lateral oblique);
* ``PatientOrientation`` as the IHE hanging stores it: ``A\\R`` (LCC), ``A\\FR`` (LMLO),
  ``P\\L`` (RCC), ``P\\FL`` (RMLO), i.e. a right breast is stored with the nipple pointing
  to the *left* of the pixel grid;
* ``ImagerPixelSpacing`` (detector) and ``PixelSpacing`` (at the breast) in mm, equal
  here because the simulated projection is orthogonal (no magnification);
* ``BitsStored`` 12 (or 14), MONOCHROME2, ``PresentationIntentType`` FOR PRESENTATION,
  ``WindowCenter``/``WindowWidth`` over the stored range.

Pixel data is JPEG 2000: lossless (``compression_ratio=None``), or lossy with the given
ratio, in which case ``LossyImageCompression`` "01", ``LossyImageCompressionRatio`` and
``LossyImageCompressionMethod`` "ISO_15444_1" are recorded as the standard requires.
Every UID derives from ``uid_seed`` so the file is reproducible byte for byte; the
dataset is de-identified with :func:`regtrack.privacy.deidentify_dataset` (DICOM PS3.15
basic profile, PatientName/ID = the pseudonym) like the project's MR series.
"""

from __future__ import annotations

import datetime
import logging
import os
from pathlib import Path

import numpy as np

from regtrack._io import atomic_path
from regtrack.errors import ConfigError

log = logging.getLogger(__name__)

MG_FOR_PRESENTATION = "1.2.840.10008.5.1.4.1.1.1.2"
#: IHE standard hanging (PatientOrientation: column direction, row direction)
IHE_ORIENTATION = {("L", "CC"): ("A", "R"), ("L", "MLO"): ("A", "FR"),
                   ("R", "CC"): ("P", "L"), ("R", "MLO"): ("P", "FL")}
#: SNOMED view codes (DICOM CID 4014)
VIEW_CODES = {"CC": ("R-10242", "cranio-caudal"), "MLO": ("R-10226", "medio-lateral oblique")}


def stored_from_canonical(image: np.ndarray, laterality: str) -> np.ndarray:
    """Pixel grid as stored under the IHE hanging: a right breast is flipped left-right.

    ``image`` is in the canonical frame of :mod:`regtrack.views` (chest wall on the left,
    nipple to the right, down = medial / infero-medial).
    """
    return np.ascontiguousarray(image[:, ::-1] if laterality == "R" else image)


def canonical_to_stored_rc(rc, *, shape: tuple[int, int], laterality: str) -> np.ndarray:
    """Map (..., 2) canonical pixel (row, col) to the stored grid (same flip as the image)."""
    rc = np.asarray(rc, float).copy()
    if laterality == "R":
        rc[..., 1] = (shape[1] - 1) - rc[..., 1]
    return rc


def _uid(seed: str, *parts: object) -> str:
    from pydicom.uid import generate_uid

    return generate_uid(entropy_srcs=[seed, *map(str, parts)])


def write_mg_dicom(path: str | os.PathLike, stored: np.ndarray, *, view: str, laterality: str,
                   spacing_mm: float, uid_seed: str, patient: str = "ANONYMOUS",
                   bits_stored: int = 12, compression_ratio: float | None = 10.0,
                   window: tuple[float, float] | None = None, series_number: int = 1,
                   instance_number: int = 1, description: str = "",
                   study_date: datetime.date | None = None) -> Path:
    """Write one mammogram (already in the stored orientation) as DICOM MG.

    Parameters
    ----------
    path : path-like
        Output file (written atomically).
    stored : (rows, cols) integer array
        Pixel values in ``[0, 2**bits_stored - 1]`` (bright = dense), stored orientation
        (see :func:`stored_from_canonical`).
    view : {"CC", "MLO"}
    laterality : {"L", "R"}
    spacing_mm : float
        Square pixel size (mm) at the detector and at the breast.
    uid_seed : str
        Seed of every UID (study, series, instance, frame of reference).
    patient : str
        Pseudonymous PatientName and PatientID.
    bits_stored : {12, 14, 16}
    compression_ratio : float or None
        JPEG 2000 lossy target ratio (uncompressed 16-bit size / compressed size); None
        for JPEG 2000 lossless.
    window : (centre, width), optional
        VOI window; default the whole stored range.

    Returns
    -------
    Path
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import JPEG2000, ExplicitVRLittleEndian, JPEG2000Lossless

    view, laterality = str(view).upper(), str(laterality).upper()
    if (laterality, view) not in IHE_ORIENTATION:
        raise ConfigError(f"{path}: view {view!r} / laterality {laterality!r}: use CC or MLO, L or R")
    if bits_stored not in (12, 14, 16):
        raise ConfigError(f"{path}: bits_stored = {bits_stored}: mammography detectors store 12, 14 or 16 bits")
    arr = np.asarray(stored)
    top = 2 ** bits_stored - 1
    if arr.ndim != 2 or arr.min() < 0 or arr.max() > top:
        raise ConfigError(f"{path}: pixel values must be a 2-D array in [0, {top}] "
                          f"(got shape {arr.shape}, range {arr.min()}..{arr.max()})")
    arr = np.ascontiguousarray(arr.astype(np.uint16))
    date = (study_date or datetime.date(2000, 1, 15)).strftime("%Y%m%d")
    sop_uid = _uid(uid_seed, "mg-sop", view, laterality)

    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = MG_FOR_PRESENTATION
    ds.file_meta.MediaStorageSOPInstanceUID = sop_uid
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID, ds.SOPInstanceUID = MG_FOR_PRESENTATION, sop_uid
    ds.Modality = "MG"
    ds.PatientName = ds.PatientID = patient
    ds.PatientBirthDate, ds.PatientSex = "", "F"
    ds.StudyInstanceUID = _uid(uid_seed, "mg-study")
    ds.SeriesInstanceUID = _uid(uid_seed, "mg-series", view, laterality)
    ds.FrameOfReferenceUID = _uid(uid_seed, "mg-for", view, laterality)
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = ds.AcquisitionDate = date
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = "120000"
    ds.StudyID, ds.AccessionNumber, ds.ReferringPhysicianName = "1", "", ""
    ds.SeriesNumber, ds.InstanceNumber = series_number, instance_number
    ds.SeriesDescription = description or f"{laterality}{view} (simulated)"
    ds.Manufacturer = "regtrack"
    ds.ManufacturerModelName = "regtrack.phantom simulated mammogram"
    ds.ImageType = ["DERIVED", "PRIMARY"]
    ds.PresentationIntentType = "FOR PRESENTATION"
    ds.BodyPartExamined = "BREAST"
    ds.ImageLaterality = laterality
    ds.ViewPosition = view
    code, meaning = VIEW_CODES[view]
    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = code, "SRT", meaning
    ds.ViewCodeSequence = [item]
    ds.PatientOrientation = list(IHE_ORIENTATION[(laterality, view)])
    ds.ImagerPixelSpacing = ds.PixelSpacing = [float(spacing_mm), float(spacing_mm)]
    ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = "LOG", 1
    ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = 0, 1, "US"
    c, w = window if window is not None else ((top + 1) / 2.0, float(top + 1))
    ds.WindowCenter, ds.WindowWidth = float(c), float(w)
    ds.VOILUTFunction = "LINEAR"
    ds.BurnedInAnnotation = "NO"
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.Rows, ds.Columns = arr.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, bits_stored, bits_stored - 1
    ds.PixelRepresentation = 0
    ds.PixelData = arr.tobytes()
    from regtrack.privacy import deidentify_dataset

    deidentify_dataset(ds, pseudonym=patient)  # DICOM PS3.15 basic profile, as the MR series
    if compression_ratio is None:
        ds.compress(JPEG2000Lossless, arr, generate_instance_uid=False)
    else:
        ds.compress(JPEG2000, arr, generate_instance_uid=False, j2k_cr=[float(compression_ratio)])
        ds.LossyImageCompression = "01"
        ratio = arr.nbytes / len(_encapsulated_payload(ds))
        ds.LossyImageCompressionRatio = f"{ratio:.2f}"
        ds.LossyImageCompressionMethod = "ISO_15444_1"
    path = Path(path)
    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
    log.info("wrote %s: %s%s, %dx%d px at %.3f mm, %s", path, laterality, view, arr.shape[0],
             arr.shape[1], spacing_mm, "JPEG 2000 lossless" if compression_ratio is None
             else f"JPEG 2000 lossy {float(ds.LossyImageCompressionRatio):.1f}:1")
    return path


def _encapsulated_payload(ds) -> bytes:
    """The JPEG 2000 codestream of a single-frame encapsulated dataset."""
    from pydicom.encaps import generate_fragmented_frames

    return b"".join(next(generate_fragmented_frames(ds.PixelData)))
