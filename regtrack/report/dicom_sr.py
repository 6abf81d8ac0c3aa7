"""Results back to the PACS: a DICOM Comprehensive SR (TID 1500) and the report as DICOM.

Per study of the input mammograms (:func:`write_dicom_results`):

* ``sr_<n>.dcm``: a Comprehensive SR (Comprehensive 3D SR when it holds the MRI points)
  holding a TID 1500 *Measurement Report* (highdicom,
  Herrmann et al., J Digit Imaging 2022).  For each mammogram and each MRI lesion:

  - a TID 1410 planar ROI group whose image region is the predicted lesion outline
    (``POLYLINE``, closed, in the mammogram's own pixel grid: column, row) referencing the
    mammogram's SOP instance, with the 1-sigma radius and the error against the annotated
    outline (paper mode) as measurements;
  - a TID 1410 group whose region is the predicted centroid (``POINT``), with the same
    measurements;
  - where the MRI is a DICOM series, one TID 1410 group per lesion whose region is its
    volume centroid in the MRI (``SCOORD3D`` ``POINT``, LPS mm, in the series' frame of
    reference), so a viewer can show the lesion on the MRI too;
  - a TID 1501 group *regtrack metrics <VIEW>* with the metrics of the view (BS_Av,
    TS_Av, theta_p, D, d_T, d_B, plate force and gap, the DICOM's force) as numeric
    measurements, referencing the mammogram as its source image.

  Concepts that have no standard code use the private coding scheme ``99REGTRACK``.
* ``report_<n>.dcm``: the PDF report as an Encapsulated PDF (PS3.3 A.45.1, SOP class
  1.2.840.10008.5.1.4.1.1.104.1) in the same study.

Both carry the study of the mammograms (StudyInstanceUID and the references), so a PACS
files them with the exam.  Unless ``keep_identifiers``, the patient module is replaced by
the case's pseudonym and every identifying attribute is removed or emptied
(:func:`regtrack.privacy.deidentify_dataset`, the PS3.15 basic profile for the attributes
written; the UIDs are kept, since they are the references).
"""

from __future__ import annotations

import datetime as _dt
import logging
import warnings
from pathlib import Path

import numpy as np

from regtrack import __version__

log = logging.getLogger(__name__)

SCHEME = "99REGTRACK"
ENCAPSULATED_PDF = "1.2.840.10008.5.1.4.1.1.104.1"

#: metrics row key -> (code value, meaning, UCUM unit, scale)
METRICS = {
    "BS_Av": ("BS_Av", "Breast similarity BS_Av", "%", 1.0),
    "TS_Av": ("TS_Av", "Tumour similarity TS_Av", "%", 1.0),
    "theta_p_b": ("theta_p_b", "Breast rotation theta_p,b", "deg", 1.0),
    "theta_p": ("theta_p", "Applied rotation theta_p", "deg", 1.0),
    "D": ("D", "Compression degree D", "%", 100.0),
    "d_T": ("d_T", "Tumour centroid distance d_T", "mm", 1.0),
    "d_B": ("d_B", "Breast centroid distance d_B", "mm", 1.0),
    "force_N": ("force_N", "Simulated plate force", "N", 1.0),
    "plate_gap_mm": ("plate_gap", "Simulated final plate gap", "mm", 1.0),
    "dicom_force_N": ("dicom_force", "Compression force of the DICOM", "N", 1.0),
    "lesion_error_mm": ("lesion_error", "Predicted lesion error against the outline", "mm", 1.0),
}


#: Type 2 patient and study attributes copied from the mammograms into the outputs
TYPE2_COPIED = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate",
                "StudyTime", "StudyID", "AccessionNumber", "ReferringPhysicianName")


def _hd():
    try:
        import highdicom
    except ImportError as err:  # pragma: no cover - a declared dependency
        from regtrack.errors import ConfigError

        raise ConfigError("writing the DICOM SR needs highdicom: pip install highdicom") from err
    return highdicom


def _code(value: str, meaning: str):
    return _hd().sr.CodedConcept(value=value, scheme_designator=SCHEME, meaning=meaning)


def _unit(unit: str):
    return _hd().sr.CodedConcept(value=unit, scheme_designator="UCUM", meaning=unit)


def _measurement(value: float, code: str, meaning: str, unit: str):
    return _hd().sr.Measurement(name=_code(code, meaning), value=float(value), unit=_unit(unit))


def _roi_group(identifier: str, region, measurements: list | None = None):
    """One TID 1410 group (planar ROI) of a lesion: its tracking identifier, the region
    (a 2-D ``ImageRegion`` on a mammogram or a 3-D ``ImageRegion3D`` in the MRI's frame)
    and the measurements attached to it."""
    hd = _hd()
    return hd.sr.PlanarROIMeasurementsAndQualitativeEvaluations(
        tracking_identifier=hd.sr.TrackingIdentifier(uid=hd.UID(), identifier=identifier),
        referenced_region=region, finding_type=hd.sr.CodedConcept("52988006", "SCT", "Lesion"),
        measurements=measurements)


def _lesion_groups(view: str, header, lesion) -> list:
    """The outline and centroid groups (TID 1410) of one lesion on one mammogram.  An
    image region must lie on its image: a lesion predicted wholly off the image has none,
    one across an edge has its outline clipped to the image and its centroid only where
    that lies on it."""
    from regtrack.tracking.lesions import OUTSIDE_IMAGE

    if OUTSIDE_IMAGE in lesion.notes:
        return []
    hd = _hd()
    src = hd.sr.SourceImageForRegion(referenced_sop_class_uid=header.SOPClassUID,
                                     referenced_sop_instance_uid=header.SOPInstanceUID)
    meas = [_measurement(lesion.sigma_mm, "sigma", "Prediction uncertainty radius (1 sigma)",
                         "mm")]
    if lesion.error_mm is not None:
        meas.append(_measurement(lesion.error_mm, "lesion_error",
                                 "Predicted lesion error against the outline", "mm"))
    name = f"MRI lesion {lesion.lesion} on {view}"
    groups = []
    size = (getattr(header, "Columns", None), getattr(header, "Rows", None))
    bounds = (float(size[0]) - 1.0, float(size[1]) - 1.0) if all(size) else None
    cr = _clipped_outline(lesion.outline_px, bounds)
    if cr is not None:
        groups.append(_roi_group(f"{name}: outline", hd.sr.ImageRegion(
            graphic_type=hd.sr.GraphicTypeValues.POLYLINE, graphic_data=cr, source_image=src),
            meas))
    if lesion.centroid_px is not None:
        c = np.asarray(lesion.centroid_px, float)[::-1][None]
        if bounds is None or ((c >= 0.0) & (c <= bounds)).all():
            groups.append(_roi_group(f"{name}: centroid", hd.sr.ImageRegion(
                graphic_type=hd.sr.GraphicTypeValues.POINT, graphic_data=c, source_image=src),
                meas))
    return groups


def _clipped_outline(outline_px, bounds) -> np.ndarray | None:
    """A closed (column, row) polyline of the (row, col) outline clipped to the pixel
    centres' rectangle ``[0, bounds[0]] x [0, bounds[1]]`` (its largest piece on the
    image; not clipped where ``bounds`` is None, a header without Rows and Columns); None
    without an outline or where no area of it is on the image."""
    from shapely.geometry import box

    from regtrack.registration.geometry import has_area, polygon

    if outline_px is None or not has_area(outline_px):
        return None
    cr = np.asarray(outline_px, float)[:, ::-1]
    if bounds is None or ((cr >= 0.0) & (cr <= bounds)).all():
        return np.vstack([cr, cr[:1]])  # wholly on the image: as predicted, closed
    g = polygon(cr).intersection(box(0.0, 0.0, *bounds))
    parts = [p for p in getattr(g, "geoms", [g]) if p.geom_type == "Polygon" and p.area > 0.0]
    if not parts:
        return None
    return np.asarray(max(parts, key=lambda p: p.area).exterior.coords, float)


def _mri_lesion_groups(results: list, frame_of_reference_uid: str) -> list:
    """One TID 1410 group per MRI lesion: its volume centroid as a 3-D point (LPS mm) in
    the MRI series' frame of reference (each lesion once, whatever the views)."""
    hd = _hd()
    points: dict[int, np.ndarray] = {}
    for r in results:
        for lesion in r.extra.get("lesions") or []:
            if lesion.mri_lps_mm is not None:
                points.setdefault(int(lesion.lesion), np.asarray(lesion.mri_lps_mm, float))
    return [_roi_group(f"MRI lesion {k} on the MRI", hd.sr.ImageRegion3D(
        graphic_type=hd.sr.GraphicTypeValues3D.POINT, graphic_data=p[None],
        frame_of_reference_uid=frame_of_reference_uid)) for k, p in sorted(points.items())]


def _metrics_group(view: str, header, row: dict):
    hd = _hd()
    meas = []
    for key, (code, meaning, unit, scale) in METRICS.items():
        v = row.get(key)
        if isinstance(v, (int, float)) and np.isfinite(v):
            meas.append(_measurement(scale * v, code, meaning, unit))
    src = hd.sr.SourceImageForMeasurementGroup(referenced_sop_class_uid=header.SOPClassUID,
                                               referenced_sop_instance_uid=header.SOPInstanceUID)
    return hd.sr.MeasurementsAndQualitativeEvaluations(
        tracking_identifier=hd.sr.TrackingIdentifier(
            uid=hd.UID(), identifier=f"regtrack metrics {view} ({row.get('mode')} mode)"),
        measurements=meas or None, source_images=[src])


def build_sr(headers: dict, results: list, *, case_id: str, series_number: int = 901,
             mri_frame_uid: str | None = None):
    """The Comprehensive SR of one study: ``headers`` {view: mammogram header dataset},
    ``results`` the pipeline's ViewOutcomes of those views, ``mri_frame_uid`` the MRI
    series' FrameOfReferenceUID (None: no MRI points)."""
    hd = _hd()
    groups = []
    for r in results:
        h = headers[r.view]
        for lesion in r.extra.get("lesions") or []:
            groups += _lesion_groups(r.view, h, lesion)
        groups.append(_metrics_group(r.view, h, r.row))
    mri_points = _mri_lesion_groups(results, mri_frame_uid) if mri_frame_uid else []
    groups += mri_points
    observer = hd.sr.ObserverContext(
        observer_type=hd.sr.CodedConcept("121007", "DCM", "Device"),
        observer_identifying_attributes=hd.sr.DeviceObserverIdentifyingAttributes(
            uid=hd.UID(), name="regtrack", model_name=f"regtrack {__version__}"))
    report = hd.sr.MeasurementReport(
        observation_context=hd.sr.ObservationContext(observer_device_context=observer),
        procedure_reported=hd.sr.CodedConcept("71651007", "SCT", "Mammography"),
        imaging_measurements=groups)
    evidence = [headers[r.view] for r in results]
    with warnings.catch_warnings():  # a one-component PatientName (a pseudonym) is intended
        warnings.filterwarnings("ignore", message=".*person name.*", category=UserWarning)
        # SCOORD3D content (the MRI points) needs the Comprehensive 3D SR SOP class
        sop = hd.sr.Comprehensive3DSR if mri_points else hd.sr.ComprehensiveSR
        sr = sop(
            evidence=evidence, content=report[0], series_instance_uid=hd.UID(),
            series_number=series_number, sop_instance_uid=hd.UID(), instance_number=1,
            manufacturer="regtrack", series_description=f"regtrack lesion tracking {case_id}")
    return sr


def build_encapsulated_pdf(pdf: bytes, header, *, case_id: str, series_number: int = 902):
    """The PDF report as an Encapsulated PDF instance in the study of ``header``."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    ds = Dataset()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ENCAPSULATED_PDF
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    for kw in ("StudyInstanceUID",) + TYPE2_COPIED:
        setattr(ds, kw, header.get(kw, ""))
    now = _dt.datetime.now()
    ds.SOPClassUID, ds.SOPInstanceUID = ENCAPSULATED_PDF, meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = "DOC", generate_uid(), series_number
    ds.InstanceNumber = 1
    ds.Manufacturer = "regtrack"
    ds.ConversionType = "WSD"  # workstation
    ds.ContentDate, ds.ContentTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ds.AcquisitionDateTime = now.strftime("%Y%m%d%H%M%S")
    ds.BurnedInAnnotation = "YES"  # the pages name the case and show the images
    ds.DocumentTitle = f"regtrack report {case_id}"[:64]
    ds.ConceptNameCodeSequence = []
    ds.MIMETypeOfEncapsulatedDocument = "application/pdf"
    ds.SeriesDescription = f"regtrack report {case_id}"[:64]
    ds.EncapsulatedDocument = pdf + (b"\0" if len(pdf) % 2 else b"")
    ds.EncapsulatedDocumentLength = len(pdf)
    return ds


def mri_frame_of_reference(series: Path | None) -> str | None:
    """The FrameOfReferenceUID of the DICOM MR series folder ``series`` (its first file
    that has one), or None (no series, or none found: a warning)."""
    import pydicom

    if series is None or not Path(series).is_dir():
        return None
    for path in sorted(p for p in Path(series).rglob("*") if p.is_file()):
        try:
            uid = pydicom.dcmread(str(path), stop_before_pixels=True).get("FrameOfReferenceUID")
        except Exception:  # not a DICOM file: the folder may hold others
            continue
        if uid:
            return str(uid)
    log.warning("[mri] series %s: no file has a FrameOfReferenceUID; the DICOM SR leaves the "
                "lesions' MRI points out", series)
    return None


def write_dicom_results(out: Path, results: list, mammograms: dict, *, case_id: str,
                        pdf_path: Path | None, keep_identifiers: bool,
                        mri_series: Path | None = None) -> list[Path]:
    """Write one SR (and one Encapsulated PDF when ``pdf_path``) per study; return the paths.

    ``mammograms`` maps each view to its DICOM file; ``mri_series`` the case's DICOM MR
    series folder, if any (the lesions' MRI points are then in the SR).  Views without a
    real mammogram or a prediction are left out; nothing is written when none remains.
    """
    import pydicom
    import pydicom.uid

    from regtrack import _io
    from regtrack.privacy import deidentify_dataset

    real = [r for r in results if r.view in mammograms and r.extra.get("mode")]
    if not real:
        return []
    headers = {r.view: pydicom.dcmread(str(mammograms[r.view]), stop_before_pixels=True)
               for r in real}
    new_study = pydicom.uid.generate_uid()
    for view, h in list(headers.items()):
        missing = [kw for kw in ("SOPClassUID", "SOPInstanceUID") if not h.get(kw)]
        if missing:
            log.warning("[views.%s] %s has no %s: the DICOM SR cannot reference it; its "
                        "predictions are left out of the SR", view, Path(mammograms[view]).name,
                        " or ".join(missing))
            del headers[view]
            continue
        for kw in ("StudyInstanceUID", "SeriesInstanceUID"):  # Type 1, absent in some exports
            if not h.get(kw):  # one new study for all the views that lack theirs
                setattr(h, kw, new_study if kw == "StudyInstanceUID" else
                        pydicom.uid.generate_uid())
                log.warning("[views.%s] %s has no %s: the DICOM results get a new one (a "
                            "PACS files them apart from the exam)", view,
                            Path(mammograms[view]).name, kw)
        for kw in TYPE2_COPIED:  # Type 2 attributes the SR copies from its evidence
            if kw not in h:
                setattr(h, kw, "")
    real = [r for r in real if r.view in headers]
    if not real:
        return []
    if not keep_identifiers:  # the SR copies the patient and study modules of its evidence
        headers = {v: deidentify_dataset(h, pseudonym=case_id) for v, h in headers.items()}
    studies: dict[str, list] = {}
    for r in real:
        studies.setdefault(str(headers[r.view].get("StudyInstanceUID", "")), []).append(r)
    paths = []
    pdf = Path(pdf_path).read_bytes() if pdf_path is not None else None
    mri_frame = mri_frame_of_reference(mri_series)
    for n, (_uid, rs) in enumerate(studies.items(), 1):
        docs = [("sr", build_sr(headers, rs, case_id=case_id,
                                mri_frame_uid=mri_frame))]
        if pdf is not None:
            docs.append(("report", build_encapsulated_pdf(pdf, headers[rs[0].view],
                                                          case_id=case_id)))
        for stem, ds in docs:
            if not keep_identifiers:
                created = (ds.ContentDate, ds.ContentTime)
                deidentify_dataset(ds, pseudonym=case_id)
                # the instance's own creation time is regtrack's, not the patient's (Type 1
                # in the SR); AcquisitionDateTime is Type 2 in the Encapsulated Document
                ds.ContentDate, ds.ContentTime = created
                if stem == "report":
                    ds.AcquisitionDateTime = ""
            path = out / "dicom" / f"{stem}_{n}.dcm"
            with _io.atomic_path(path) as tmp:
                ds.save_as(tmp, enforce_file_format=True)
            paths.append(path)
    log.info("DICOM results: %s", ", ".join(p.name for p in paths))
    return paths
