"""Results back to the PACS (issue 52): the TID 1500 SR and the encapsulated PDF, read back.

The SR is written from a hand-made prediction on two mammogram headers, then read back
with highdicom: the outline's points (column, row) and the centroid are those given, each
region references its mammogram's SOP instance, the measurements carry their values and
units, and the patient's identifiers are replaced by the pseudonym (unless kept).
``dciodvfy`` (Debian dicom3tools) validates both files when it is installed.
"""

from __future__ import annotations

import shutil
import subprocess
from types import SimpleNamespace

import numpy as np
import pydicom
import pytest

from regtrack.privacy import dicom_leaks
from regtrack.tracking.lesions import LesionPrediction
from tests.test_mammogram_geometry import _ds, _write

hd = pytest.importorskip("highdicom")

STUDY = pydicom.uid.generate_uid()


def _header(tmp_path, view):
    ds = _ds(BodyPartThickness=50)
    ds.PatientName, ds.PatientID, ds.PatientBirthDate = "Doe^Jane", "MRN12345", "19600101"
    ds.InstitutionName, ds.AccessionNumber = "General Hospital", "ACC999"
    ds.StudyInstanceUID, ds.SeriesInstanceUID = STUDY, pydicom.uid.generate_uid()
    ds.StudyDate, ds.StudyTime, ds.ViewPosition = "20240102", "101010", view
    return _write(tmp_path / f"{view.lower()}.dcm", ds)


def _outcome(view, error):
    rc = np.array([[100.0, 200.0], [100.0, 240.0], [130.0, 240.0], [130.0, 200.0]])
    les = LesionPrediction(view, 1, np.array([22.0, 11.5]), np.array([115.0, 220.0]), rc * 0.1,
                           2.5, {"registration_residual": 1.0, "rotation": 0.5, "model": 2.0},
                           1.0, 0.2, 50.0, 5.0, error_mm=error, outline_px=rc)
    row = {"view": view, "mode": "paper" if error is not None else "tracking", "BS_Av": 70.0,
           "TS_Av": None, "theta_p": 1.5, "D": 0.38, "d_B": 4.0, "force_N": 60.0,
           "lesion_error_mm": error}
    return SimpleNamespace(view=view, row=row, extra={"mode": row["mode"], "lesions": [les]})


@pytest.mark.parametrize("keep", [False, True])
def test_sr_and_pdf_read_back(tmp_path, keep):
    from regtrack.report.dicom_sr import write_dicom_results

    mammos = {"CC": _header(tmp_path, "CC"), "MLO": _header(tmp_path, "MLO")}
    pdf = tmp_path / "report.pdf"
    pdf.write_bytes(b"%PDF-1.4\n% a tiny stand-in\n%%EOF\n")
    paths = write_dicom_results(tmp_path / "out", [_outcome("CC", 1.25), _outcome("MLO", None)],
                                mammos, case_id="anon-1234", pdf_path=pdf, keep_identifiers=keep)
    assert [p.name for p in paths] == ["sr_1.dcm", "report_1.dcm"]  # one study
    sr_path, doc_path = paths

    sr = hd.sr.srread(sr_path)
    assert sr.StudyInstanceUID == STUDY and sr.Modality == "SR"
    uids = {v: pydicom.dcmread(p).SOPInstanceUID for v, p in mammos.items()}
    groups = sr.content.get_planar_roi_measurement_groups()
    assert len(groups) == 4  # outline + centroid per view
    by_id = {str(g.tracking_identifier): g for g in groups}
    for view in ("CC", "MLO"):
        outline = by_id[f"MRI lesion 1 on {view}: outline"]
        assert outline.roi.graphic_type == hd.sr.GraphicTypeValues.POLYLINE
        pts = outline.roi.value
        np.testing.assert_allclose(pts[0], [200.0, 100.0])  # (column, row)
        np.testing.assert_allclose(pts[-1], pts[0])          # closed
        ref = outline.roi.ContentSequence[0].ReferencedSOPSequence[0]
        assert ref.ReferencedSOPInstanceUID == uids[view]
        centroid = by_id[f"MRI lesion 1 on {view}: centroid"]
        np.testing.assert_allclose(np.asarray(centroid.roi.value).reshape(-1), [220.0, 115.0])
        meas = {m.name.value: (m.value, m.unit.value) for m in centroid.get_measurements()}
        assert meas["sigma"] == (pytest.approx(2.5), "mm")
        assert ("lesion_error" in meas) == (view == "CC")
    metrics = {str(g.tracking_identifier): g for g in sr.content.get_image_measurement_groups()}
    cc = {m.name.value: (m.value, m.unit.value)
          for m in metrics["regtrack metrics CC (paper mode)"].get_measurements()}
    assert cc["BS_Av"] == (pytest.approx(70.0), "%") and cc["D"] == (pytest.approx(38.0), "%")
    assert "TS_Av" not in cc  # absent metrics are left out, never NaN

    doc = pydicom.dcmread(doc_path)
    assert doc.SOPClassUID == "1.2.840.10008.5.1.4.1.1.104.1" and doc.StudyInstanceUID == STUDY
    assert doc.EncapsulatedDocument[:doc.EncapsulatedDocumentLength] == pdf.read_bytes()
    for p in paths:
        if keep:
            assert pydicom.dcmread(p).PatientID == "MRN12345"
        else:
            assert dicom_leaks(p, pseudonym="anon-1234") == []
            assert b"Doe" not in p.read_bytes() and b"MRN12345" not in p.read_bytes()
        if shutil.which("dciodvfy"):
            out = subprocess.run(["dciodvfy", str(p)], check=False, capture_output=True, text=True)
            errors = [x for x in (out.stdout + out.stderr).splitlines() if x.startswith("Error")]
            assert errors == [], errors


def test_mri_lesion_is_a_3d_point_in_the_mri_frame_of_reference(tmp_path):
    """Where the MRI is a DICOM series, each lesion's MRI centroid is one SCOORD3D point
    (LPS mm) in the series' frame of reference, once whatever the number of views; without
    a series (a NIfTI label map alone) there is none."""
    from regtrack.report.dicom_sr import write_dicom_results

    series = tmp_path / "mri"
    series.mkdir()
    (series / "notes.txt").write_text("not DICOM")
    mr = _ds()
    mr.FrameOfReferenceUID = for_uid = pydicom.uid.generate_uid()
    _write(series / "slice001.dcm", mr)
    mammos = {"CC": _header(tmp_path, "CC"), "MLO": _header(tmp_path, "MLO")}
    outcomes = [_outcome("CC", 1.25), _outcome("MLO", None)]
    for o in outcomes:
        o.extra["lesions"][0].mri_lps_mm = np.array([-40.5, 12.25, 7.0])
    for mri, n_points in ((series, 1), (None, 0)):
        out = tmp_path / ("with" if mri else "without")
        sr_path = write_dicom_results(out, outcomes, mammos, case_id="anon-1234", pdf_path=None,
                                      keep_identifiers=False, mri_series=mri)[0]
        groups = hd.sr.srread(sr_path).content.get_planar_roi_measurement_groups()
        points = [g for g in groups if isinstance(g.roi, hd.sr.ImageRegion3D)]
        assert len(points) == n_points and len(groups) == 4 + n_points
        for g in points:
            assert str(g.tracking_identifier) == "MRI lesion 1 on the MRI"
            assert g.roi.graphic_type == hd.sr.GraphicTypeValues3D.POINT
            assert g.roi.frame_of_reference_uid == for_uid
            np.testing.assert_allclose(np.asarray(g.roi.value).reshape(-1), [-40.5, 12.25, 7.0])
        if shutil.which("dciodvfy"):
            res = subprocess.run(["dciodvfy", str(sr_path)], check=False, capture_output=True,
                                 text=True)
            errors = [x for x in (res.stdout + res.stderr).splitlines() if x.startswith("Error")]
            assert errors == [], errors


def test_headers_without_study_or_instance_uids(tmp_path, caplog):
    """A study UID missing from both views: one new study, one SR, a warning naming the tag;
    a view without a SOPInstanceUID cannot be referenced and is left out, named."""
    from regtrack.report.dicom_sr import write_dicom_results

    mammos = {}
    for view in ("CC", "MLO"):
        p = _header(tmp_path, view)
        ds = pydicom.dcmread(p)
        del ds.StudyInstanceUID
        ds.save_as(p)
        mammos[view] = p
    outs = [_outcome("CC", None), _outcome("MLO", None)]
    paths = write_dicom_results(tmp_path / "a", outs, mammos, case_id="anon-1", pdf_path=None,
                                keep_identifiers=False)
    assert [p.name for p in paths] == ["sr_1.dcm"]
    sr = hd.sr.srread(paths[0])
    assert sr.StudyInstanceUID != STUDY and len(sr.content.get_planar_roi_measurement_groups()) == 4
    assert any("StudyInstanceUID" in r.message for r in caplog.records)
    ds = pydicom.dcmread(mammos["MLO"])
    del ds.SOPInstanceUID
    ds.save_as(mammos["MLO"], enforce_file_format=False)
    paths = write_dicom_results(tmp_path / "b", outs, mammos, case_id="anon-1", pdf_path=None,
                                keep_identifiers=False)
    groups = hd.sr.srread(paths[0]).content.get_planar_roi_measurement_groups()
    assert {str(g.tracking_identifier).split(" on ")[1][:2] for g in groups} == {"CC"}
    assert any("SOPInstanceUID" in r.message for r in caplog.records)


def test_a_lesion_predicted_off_the_image_has_no_region_on_it(tmp_path):
    """A lesion of the model that falls beyond the mammogram's edge is not written as an
    image region of that mammogram (its coordinates would lie off the image); the other
    lesions and the metrics are."""
    from regtrack.report.dicom_sr import write_dicom_results
    from regtrack.tracking.lesions import OUTSIDE_IMAGE

    off = _outcome("CC", None)
    inside = off.extra["lesions"][0]
    outside = LesionPrediction("CC", 2, np.array([-6.0, 140.0]), np.array([1400.0, -60.0]), None,
                               4.0, {}, 1.0, 0.2, 90.0, 0.0, notes=[OUTSIDE_IMAGE])
    off.extra["lesions"] = [inside, outside]
    paths = write_dicom_results(tmp_path / "out", [off], {"CC": _header(tmp_path, "CC")},
                                case_id="anon-1", pdf_path=None, keep_identifiers=False)
    groups = hd.sr.srread(paths[0]).content.get_planar_roi_measurement_groups()
    assert sorted(str(g.tracking_identifier) for g in groups) == [
        "MRI lesion 1 on CC: centroid", "MRI lesion 1 on CC: outline"]


def test_a_lesion_across_the_image_edge_is_clipped_to_the_image(tmp_path):
    """A predicted outline that crosses the image's last column is written clipped to the
    image (every point on it, the area of the part on the image), and its centroid only
    where that lies on the image."""
    from shapely.geometry import Polygon

    from regtrack.report.dicom_sr import write_dicom_results

    ds = pydicom.dcmread(_header(tmp_path, "CC"))
    ds.Rows, ds.Columns = 300, 230  # the outline spans columns 200-240
    header = _write(tmp_path / "cc_small.dcm", ds)
    out = _outcome("CC", None)
    shifted = LesionPrediction("CC", 2, np.array([23.5, 11.5]), np.array([115.0, 235.0]), None,
                               2.5, {}, 1.0, 0.2, 50.0, 5.0,
                               outline_px=out.extra["lesions"][0].outline_px + [0.0, 15.0])
    out.extra["lesions"].append(shifted)
    paths = write_dicom_results(tmp_path / "out", [out], {"CC": header}, case_id="anon-1",
                                pdf_path=None, keep_identifiers=False)
    groups = hd.sr.srread(paths[0]).content.get_planar_roi_measurement_groups()
    names = sorted(str(g.tracking_identifier) for g in groups)
    assert names == ["MRI lesion 1 on CC: centroid", "MRI lesion 1 on CC: outline",
                     "MRI lesion 2 on CC: outline"]  # lesion 2's centroid (column 235) is off
    for g in groups:
        if str(g.tracking_identifier).endswith("outline"):
            cr = np.asarray(g.roi.value, float)
            assert (cr[:, 0] <= 229.0).all() and (cr[:, 1] <= 299.0).all()
            first = str(g.tracking_identifier).startswith("MRI lesion 1")
            # columns 200-229 of 200-240 (lesion 1), 215-229 of 215-255 (lesion 2); rows 100-130
            assert Polygon(cr).area == pytest.approx((29.0 if first else 14.0) * 30.0)
