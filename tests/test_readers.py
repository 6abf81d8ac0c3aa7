"""Volume readers/writers: affines against real MetaImage headers, round trips, bad inputs.

Real data: Pelicano et al., *Sensors* 2021 and *PLoS One* 2024 (MRI-derived breast label
maps, ../shared/data/pelicano), reached only through ``shared_data``.
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from regtrack.errors import InputFileError
from regtrack.imaging.readers import (
    read_image_volume,
    read_label_map,
    write_dicom_series,
    write_image_volume,
    write_label_map,
)
from regtrack.imaging.volume import ImageVolume, LabelVolume, make_affine

from conftest import SAMPLE_CASES, shared_data


def _rotation(ax_deg=20.0, ay_deg=-35.0, az_deg=50.0) -> np.ndarray:
    a, b, c = np.radians([ax_deg, ay_deg, az_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


OBLIQUE = make_affine([-12.5, 40.25, 7.0], [0.5, 0.7, 1.3], _rotation())


def _labels(shape=(40, 36, 12), seed=0) -> LabelVolume:
    rng = np.random.default_rng(seed)
    return LabelVolume(rng.integers(-4, 8, shape).astype(np.int16), OBLIQUE.copy())


# ----------------------------------------------------------------------------- real exams


def _mha_header(zip_path) -> dict:
    """MetaImage header fields of the one .mha in a zip (read as text, independently of ITK)."""
    with zipfile.ZipFile(zip_path) as zf, zf.open(zf.namelist()[0]) as f:
        head = f.read(2048).split(b"ElementDataFile")[0].decode("ascii")
    fields = dict(line.split(" = ", 1) for line in head.strip().splitlines())
    return {k: v.split() for k, v in fields.items()}


@pytest.mark.realdata
@pytest.mark.parametrize("exam,name", [("Exam_03", "label_map_simple.zip"),  # MET_FLOAT
                                       ("Exam_11", "Label_map_simple.zip")])  # MET_SHORT
def test_affine_matches_metaimage_header(exam, name):
    """affine == header: Offset = voxel (0,0,0), ElementSpacing, TransformMatrix column-major.

    The Pelicano TransformMatrix ``1 0 0 0 0 -1 0 1 0`` is not symmetric, so the test tells
    the two readings apart: SimpleITK (and we) take the LPS direction of array axis ``a`` as
    ``m[3a : 3a + 3]``, i.e. direction = transpose of the matrix read row-major.
    """
    path = shared_data("pelicano", exam, name)
    hdr = _mha_header(path)
    vol = read_label_map(path, label_dtype=np.int8)
    tm = np.array(hdr["TransformMatrix"], float)
    spacing = np.array(hdr["ElementSpacing"], float)
    assert vol.shape == tuple(int(v) for v in hdr["DimSize"])
    np.testing.assert_allclose(vol.origin, np.array(hdr["Offset"], float), atol=1e-9)
    np.testing.assert_allclose(vol.spacing, spacing, rtol=1e-12)
    np.testing.assert_allclose(vol.direction, tm.reshape(3, 3).T, atol=1e-12)
    assert not np.allclose(vol.direction, tm.reshape(3, 3))
    # the same mapping written out: x = Offset + sum_a i_a * spacing_a * m[3a:3a+3]
    ijk = np.array([17, 5, 101])
    expect = np.array(hdr["Offset"], float) + sum(ijk[a] * spacing[a] * tm[3 * a: 3 * a + 3] for a in range(3))
    np.testing.assert_allclose(vol.index_to_world(ijk), expect, atol=1e-9)


@pytest.mark.realdata
def test_real_exam_anatomy_is_consistent_with_lps():
    """Exam 03: published tumour in the right breast (LPS x below the body centre), and the
    breasts hang anterior of the pectoral muscle (smaller LPS y).  Tumour volume near the
    published 8.5 x 11.2 x 9.2 mm ellipsoid (458 mm^3); 25 % allows for the irregular shape."""
    vol = read_label_map(shared_data("pelicano", "Exam_03", "label_map_simple.zip"))
    assert vol.meta["source_dtype"] == "float32"
    assert set(np.unique(vol.data)) == {-3, -2, -1, 0, 1}
    world = lambda lab: vol.index_to_world(np.argwhere(vol.data == lab))  # noqa: E731
    tumour, muscle, tissue = world(-3), world(-1), world(1)
    assert tumour[:, 0].mean() < tissue[:, 0].mean()
    assert np.percentile(tissue[:, 1], 5) < np.percentile(muscle[:, 1], 5) - 30.0
    v_t = len(tumour) * vol.voxel_volume
    assert v_t == pytest.approx(np.pi / 6 * 8.5 * 11.2 * 9.2, rel=0.25)


@pytest.mark.realdata
def test_bundled_pelicano_crop_keeps_labels_and_geometry():
    """sample_cases/pelicano_exam03 is an exact sub-block of the real exam, same LPS mapping."""
    src = read_label_map(shared_data("pelicano", "Exam_03", "label_map_simple.zip"), label_dtype=np.int8)
    case = SAMPLE_CASES / "pelicano_exam03"
    prov = json.loads((case / "provenance.json").read_text())
    crop = read_label_map(case / "mri" / "labels.nii.gz")
    lo, hi = prov["index_lo"], prov["index_hi"]
    np.testing.assert_array_equal(crop.data, src.data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
    # NIfTI stores the affine in float32: 1e-4 mm
    np.testing.assert_allclose(crop.affine, src.crop(lo, hi).affine, atol=1e-4)
    assert (crop.data == -3).sum() == (src.data == -3).sum()  # the whole tumour is inside
    assert prov["side"] == "R"


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("name", ["l.nii.gz", "l.nii", "l.mha", "l.nrrd"])
def test_label_map_round_trip(tmp_path, name):
    vol = _labels()
    write_label_map(vol, tmp_path / name)
    back = read_label_map(tmp_path / name)
    np.testing.assert_array_equal(back.data, vol.data)
    # NIfTI keeps the affine in float32 (qform/sform): 1e-4 mm; MHA/NRRD are exact text
    np.testing.assert_allclose(back.affine, vol.affine, atol=1e-4 if ".nii" in name else 1e-9)
    assert back.data.dtype == np.int16
    assert [p.name for p in tmp_path.iterdir()] == [name]  # no temporary left


def test_label_map_written_as_int8_when_it_fits(tmp_path):
    write_label_map(_labels(), tmp_path / "l.mha")
    assert sitk.ReadImage(str(tmp_path / "l.mha")).GetPixelID() == sitk.sitkInt8


def test_mhd_with_separate_raw_and_zipped(tmp_path):
    vol = _labels()
    img = sitk.GetImageFromArray(vol.data.transpose(2, 1, 0).astype(np.float32))
    img.SetOrigin(vol.origin.tolist())
    img.SetSpacing(vol.spacing.tolist())
    img.SetDirection(vol.direction.ravel().tolist())
    sitk.WriteImage(img, str(tmp_path / "v.mhd"))
    back = read_label_map(tmp_path / "v.mhd")
    np.testing.assert_array_equal(back.data, vol.data)
    with zipfile.ZipFile(tmp_path / "v.zip", "w") as zf:
        for f in ("v.mhd", "v.raw"):
            zf.write(tmp_path / f, f"sub/{f}")
    back = read_label_map(tmp_path / "v.zip")
    np.testing.assert_array_equal(back.data, vol.data)
    np.testing.assert_allclose(back.affine, vol.affine, atol=1e-9)


def test_zipped_float_mha_like_pelicano(tmp_path):
    vol = _labels()
    write_image_volume(ImageVolume(vol.data.astype(np.float32), vol.affine), tmp_path / "x.mha")
    with zipfile.ZipFile(tmp_path / "x.zip", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.write(tmp_path / "x.mha", "Label_map_simple.mha")
    back = read_label_map(tmp_path / "x.zip", label_dtype=np.int8)
    assert back.data.dtype == np.int8
    np.testing.assert_array_equal(back.data, vol.data)
    img = read_image_volume(tmp_path / "x.zip")
    assert img.data.dtype == np.float32
    np.testing.assert_allclose(img.affine, vol.affine, atol=1e-9)


# ----------------------------------------------------------------------------- bad inputs


def _float_map(tmp_path, values: np.ndarray, name="bad.mha"):
    img = ImageVolume(values.astype(np.float32), OBLIQUE)
    write_image_volume(img, tmp_path / name)
    return tmp_path / name


@pytest.mark.parametrize("value,match", [(0.5, "labels are not integers"), (np.nan, "NaN")])
def test_float_labels_must_be_integral(tmp_path, value, match):
    data = np.zeros((8, 8, 8))
    data[3, 4, 5] = value
    path = _float_map(tmp_path, data)
    with pytest.raises(InputFileError, match=match) as e:
        read_label_map(path)
    assert "bad.mha" in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("setup,match", [
    (lambda p: p / "missing.nii.gz", "not found"),
    (lambda p: (p / "x.vtk").write_text("no") and p / "x.vtk", "unknown volume format"),
    (lambda p: (p / "x.nii.gz").write_bytes(b"garbage") and p / "x.nii.gz", "cannot read"),
    (lambda p: (p / "x.zip").write_bytes(b"garbage") and p / "x.zip", "not a readable zip"),
])
def test_unreadable_inputs_name_the_file(tmp_path, setup, match):
    path = setup(tmp_path)
    with pytest.raises(InputFileError, match=match) as e:
        read_label_map(path)
    assert path.name in str(e.value)


def test_zip_must_hold_exactly_one_image(tmp_path):
    write_label_map(_labels(), tmp_path / "a.mha")
    with zipfile.ZipFile(tmp_path / "two.zip", "w") as zf:
        zf.write(tmp_path / "a.mha", "a.mha")
        zf.write(tmp_path / "a.mha", "b.mha")
    with zipfile.ZipFile(tmp_path / "none.zip", "w") as zf:
        zf.writestr("readme.txt", "hello")
    for name in ("two.zip", "none.zip"):
        with pytest.raises(InputFileError, match="exactly one image") as e:
            read_label_map(tmp_path / name)
        assert name in str(e.value)


def test_label_values_outside_dtype(tmp_path):
    path = _float_map(tmp_path, np.full((4, 4, 4), 300.0))
    with pytest.raises(InputFileError, match="outside int8"):
        read_label_map(path, label_dtype=np.int8)


# ----------------------------------------------------------------------------- DICOM


@pytest.mark.parametrize("ts", ["jpeg2000", "rle", "explicit"])
def test_dicom_series_round_trip_and_geometry_tags(tmp_path, ts):
    rng = np.random.default_rng(1)
    vol = ImageVolume(rng.integers(0, 4096, (40, 36, 9)).astype(np.float32), OBLIQUE)
    files = write_dicom_series(vol, tmp_path / "s", transfer_syntax=ts, patient="P1")
    for k in (0, 4, 8):
        ds = pydicom.dcmread(files[k])
        np.testing.assert_allclose(ds.ImagePositionPatient, (vol.affine @ [0, 0, k, 1])[:3], atol=1e-9)
        np.testing.assert_allclose(ds.ImageOrientationPatient, np.r_[vol.direction[:, 0], vol.direction[:, 1]], atol=1e-12)
        np.testing.assert_allclose(ds.PixelSpacing, [0.7, 0.5])  # [row spacing, column spacing]
        assert float(ds.SliceThickness) == pytest.approx(1.3)
        assert (ds.Rows, ds.Columns) == (36, 40)
        assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.4"
    back = read_image_volume(tmp_path / "s")
    np.testing.assert_array_equal(back.data, vol.data)
    np.testing.assert_allclose(back.affine, vol.affine, atol=1e-6)


def test_dicom_series_agrees_with_simpleitk_gdcm(tmp_path):
    """Independent reader (ITK/GDCM) gives the same origin, spacing, direction and voxels."""
    rng = np.random.default_rng(2)
    vol = ImageVolume(rng.integers(0, 1000, (40, 36, 7)).astype(np.float32), OBLIQUE)
    write_dicom_series(vol, tmp_path / "s", transfer_syntax="explicit")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(tmp_path / "s")))
    img = reader.Execute()
    np.testing.assert_allclose(img.GetOrigin(), vol.origin, atol=1e-4)
    np.testing.assert_allclose(img.GetSpacing(), vol.spacing, atol=1e-4)
    np.testing.assert_allclose(np.reshape(img.GetDirection(), (3, 3)), vol.direction, atol=1e-4)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img).transpose(2, 1, 0), vol.data)


def test_dicom_float_data_uses_rescale(tmp_path):
    rng = np.random.default_rng(3)
    data = rng.normal(0.0, 50.0, (36, 36, 4))
    write_dicom_series(ImageVolume(data, OBLIQUE), tmp_path / "s", transfer_syntax="rle")
    back = read_image_volume(tmp_path / "s")
    slope = (data.max() - data.min()) / 65535
    assert np.abs(back.data - data).max() <= slope / 2 + 1e-3  # float32 output


def test_dicom_slices_sorted_by_position_not_name(tmp_path):
    vol = ImageVolume(np.arange(40 * 36 * 6, dtype=np.float32).reshape(40, 36, 6), OBLIQUE)
    files = write_dicom_series(vol, tmp_path / "s", transfer_syntax="rle")
    for i, f in enumerate(files):  # reverse the name order
        f.rename(f.with_name(f"z{len(files) - i:03d}.dcm"))
    (tmp_path / "s" / "notes.txt").write_text("not DICOM")
    back = read_image_volume(tmp_path / "s")
    np.testing.assert_array_equal(back.data, vol.data)


def test_dicom_label_series_with_negative_labels(tmp_path):
    lab = _labels()
    write_dicom_series(lab, tmp_path / "s", transfer_syntax="rle")
    assert pydicom.dcmread(next((tmp_path / "s").iterdir())).PixelRepresentation == 1
    back = read_label_map(tmp_path / "s")
    np.testing.assert_array_equal(back.data, lab.data)


def _series(tmp_path, n=5):
    vol = ImageVolume(np.ones((36, 36, n), np.float32), OBLIQUE)
    return write_dicom_series(vol, tmp_path / "s", transfer_syntax="rle")


def test_dicom_missing_slice_is_an_error(tmp_path):
    files = _series(tmp_path)
    os.remove(files[2])
    with pytest.raises(InputFileError, match="uniform slice") as e:
        read_image_volume(tmp_path / "s")
    assert "slice_" in str(e.value)


def test_dicom_inconsistent_orientation_names_the_file(tmp_path):
    files = _series(tmp_path)
    ds = pydicom.dcmread(files[3])
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.save_as(files[3])
    with pytest.raises(InputFileError, match="ImageOrientationPatient") as e:
        read_image_volume(tmp_path / "s")
    assert files[3].name in str(e.value)


def test_dicom_missing_geometry_tag(tmp_path):
    files = _series(tmp_path)
    ds = pydicom.dcmread(files[1])
    del ds.ImagePositionPatient
    ds.save_as(files[1])
    with pytest.raises(InputFileError, match="ImagePositionPatient is missing"):
        read_image_volume(tmp_path / "s")


def test_dicom_two_series_in_one_folder(tmp_path):
    files = _series(tmp_path)
    ds = pydicom.dcmread(files[0])
    ds.SeriesInstanceUID = pydicom.uid.generate_uid()
    ds.save_as(files[0])
    with pytest.raises(InputFileError, match="2 DICOM series"):
        read_image_volume(tmp_path / "s")
    back = read_image_volume(tmp_path / "s", series_uid=ds.SeriesInstanceUID)
    assert back.shape == (36, 36, 1)


def test_empty_dicom_folder(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(InputFileError, match="no DICOM image files"):
        read_image_volume(tmp_path / "d")


# ----------------------------------------------------------------------------- sample cases


@pytest.mark.parametrize("case", ["phantom01", "phantom02", "pelicano_exam03"])
def test_sample_case_sizes(case):
    folder = SAMPLE_CASES / case
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    assert 0 < size < 5e6
    labels = folder / "mri" / "labels.nii.gz"
    assert labels.stat().st_size < 2e6
    assert sitk.ReadImage(str(labels)).GetPixelID() == sitk.sitkInt8


def test_phantom01_series_and_labels_share_the_grid():
    folder = SAMPLE_CASES / "phantom01" / "mri"
    mri = read_image_volume(folder / "dicom")
    lab = read_label_map(folder / "labels.nii.gz")
    assert mri.shape == lab.shape
    np.testing.assert_allclose(mri.affine, lab.affine, atol=1e-4)
    np.testing.assert_allclose(mri.spacing, [0.66, 0.66, 1.4], atol=1e-6)
    assert mri.meta["modality"] == "MR"
