"""Landmarks and the warped MRI through a known deformation (issue 55, items 2 and 3).

Known answers: a mesh moved by a rigid motion, or stretched uniformly, is an affine map,
which the linear (P1) finite-element interpolation represents exactly.  So

* the forward map of a point is the affine image of it (to round-off), and the inverse
  map composed with the forward one returns every point (the acceptance bound is 0.1 mm;
  both are exact up to round-off here);
* the label map warped through the mesh equals the label map resampled through the
  analytic inverse map with the same nearest-neighbour rule: Dice >= 0.99 per label
  (the acceptance; only a voxel centre pulled back to a tie between two input voxels
  can differ, at round-off);
* the warped ellipsoid's centroid is the affine image of the input ellipsoid's centroid
  within half a voxel (0.5 mm: the voxelisation of the input).

The model frame is rotated and shifted against LPS and the label grid has a non-identity
direction, so every frame conversion is on the path.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from regtrack.errors import TrackingError
from regtrack.imaging.volume import LabelVolume, make_affine
from regtrack.mechanics.meshes import box_model
from regtrack.model.types import AnatomicalFrame
from regtrack.tracking.deformation import DeformationMap
from regtrack.tracking.landmarks import read_landmarks
from regtrack.tracking.warp import warp_volume


def _rotation(axis, deg):
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return Rotation.from_rotvec(np.deg2rad(deg) * axis).as_matrix()


FRAME = AnatomicalFrame(origin=np.array([-90.0, -40.0, 12.0]), axes=_rotation([1, 2, 3], 35.0),
                        side="R")
MOTIONS = {
    "rigid": (_rotation([0.3, -1.0, 0.5], 20.0), np.array([3.0, -2.0, 1.5])),
    "stretch": (np.diag([1.15, 0.9, 0.85]), np.zeros(3)),
}


@pytest.fixture(scope="module")
def box():
    m = box_model((40.0, 30.0, 24.0), (8, 6, 6), origin=(-20.0, -15.0, -12.0))
    return dataclasses.replace(m, frame=FRAME)


@pytest.fixture(scope="module")
def labels(box):
    """1 mm label map: an ellipsoid (1) with a sphere (2) in the box, 3 outside the box."""
    direction = np.diag([-1.0, -1.0, 1.0])  # a NIfTI written from RAS
    corner = FRAME.to_patient(box.points).min(axis=0) - 8.0
    shape = tuple(int(v) for v in np.ceil(np.ptp(FRAME.to_patient(box.points), axis=0) + 16.0))
    # voxel (0, 0, 0) at the largest x and y: the direction flips them
    origin = np.array([corner[0] + shape[0] - 1, corner[1] + shape[1] - 1, corner[2]])
    affine = make_affine(origin, (1.0, 1.0, 1.0), direction)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    X = FRAME.to_model(ijk @ affine[:3, :3].T + affine[:3, 3])
    data = np.zeros(len(X), np.int16)
    inbox = np.all((X > box.points.min(0)) & (X < box.points.max(0)), axis=1)
    data[~inbox] = 3
    data[(((X - [1.0, -2.0, 0.5]) / [14.0, 9.0, 7.0]) ** 2).sum(1) <= 1] = 1
    data[np.linalg.norm(X - [6.0, 1.0, 1.0], axis=1) <= 4.0] = 2
    return LabelVolume(data=data.reshape(shape), affine=affine)


def _dmap(box, name):
    A, t = MOTIONS[name]
    return DeformationMap.from_model(box, box.points @ A.T + t, view=name), A, t


@pytest.mark.parametrize("name", list(MOTIONS))
def test_forward_and_inverse_are_the_affine_map(box, name):
    dmap, A, t = _dmap(box, name)
    rng = np.random.default_rng(5)
    X = rng.uniform(box.points.min(0) + 0.5, box.points.max(0) - 0.5, size=(200, 3))
    lps = FRAME.to_patient(X)
    fwd = dmap.forward(lps)
    np.testing.assert_allclose(fwd, FRAME.to_patient(X @ A.T + t), atol=1e-9)
    back = dmap.inverse(fwd)
    assert np.linalg.norm(back - lps, axis=1).max() < 0.1  # acceptance; measured ~1e-13 mm
    np.testing.assert_allclose(back, lps, atol=1e-9)


def test_points_outside_the_breast_are_refused(box):
    dmap, _, _ = _dmap(box, "rigid")
    far = FRAME.to_patient(np.array([[0.0, 0.0, 0.0], [60.0, 0.0, 0.0]]))
    with pytest.raises(TrackingError, match=r"point B \(.*\) LPS mm is outside the MRI breast "
                                            r"model, .* mm from its nearest node; give a point "
                                            "inside the breast"):
        dmap.forward(far, names=["A", "B"])
    with pytest.raises(TrackingError, match="outside the compressed rigid breast model"):
        dmap.inverse(far)


def _dice(a, b):
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


@pytest.mark.parametrize("name", list(MOTIONS))
def test_warped_label_map_matches_the_analytic_warp(box, labels, name):
    from scipy.ndimage import map_coordinates

    dmap, A, t = _dmap(box, name)
    w = warp_volume(labels, dmap)
    out = w.volume
    assert isinstance(out, LabelVolume) and out.data.dtype == labels.data.dtype
    # analytic warp: every output voxel centre pulled back through the inverse affine map
    shape = out.data.shape
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    x = FRAME.to_model(ijk @ out.affine[:3, :3].T + out.affine[:3, 3])
    X = np.linalg.solve(A, (x - t).T).T
    inbox = np.all((X >= box.points.min(0)) & (X <= box.points.max(0)), axis=1)
    inv = np.linalg.inv(labels.affine)
    src = FRAME.to_patient(X) @ inv[:3, :3].T + inv[:3, 3]
    ref = map_coordinates(labels.data, src.T, order=0, mode="constant", cval=0, prefilter=False)
    ref[~inbox] = 0
    ref = ref.reshape(shape)
    # outside the deformed model: background (the input's label 3 there is not carried);
    # inside it, next to its surface, a voxel may pull back to a label-3 input voxel
    assert (out.data.reshape(-1)[~inbox] == 0).all()
    for lab in (1, 2):
        assert (ref == lab).sum() > 100
        assert _dice(out.data == lab, ref == lab) >= 0.99, lab
    # the warped ellipsoid's centroid is the affine image of the input's (half a voxel)
    def centroid(vol, lab):
        ijk = np.argwhere(vol.data == lab)
        return FRAME.to_model(ijk.mean(0) @ vol.affine[:3, :3].T + vol.affine[:3, 3])
    c0 = centroid(labels, 1)
    assert np.linalg.norm(centroid(out, 1) - (A @ c0 + t)) < 0.5


def test_warped_label_map_round_trips_through_nifti(box, labels, tmp_path):
    from regtrack.imaging.readers import read_label_map, write_label_map

    dmap, _, _ = _dmap(box, "stretch")
    w = warp_volume(labels, dmap)
    path = write_label_map(w.volume, tmp_path / "warped.nii.gz")
    back = read_label_map(path)
    np.testing.assert_array_equal(back.data, w.volume.data)
    np.testing.assert_allclose(back.affine, w.volume.affine, atol=1e-4)


# -- landmark files -------------------------------------------------------------------------
def test_landmarks_csv_with_and_without_header(tmp_path):
    a = tmp_path / "a.csv"
    a.write_text("name,x,y,z\ncyst,-10.5,2,3\nclip, 1, 2, 3.25\n")
    lm = read_landmarks(a)
    assert lm.names == ("cyst", "clip")
    np.testing.assert_allclose(lm.lps_mm, [[-10.5, 2, 3], [1, 2, 3.25]])
    b = tmp_path / "b.csv"
    b.write_text("# LPS mm\n1,2,3\n4,5,6\n")
    lm = read_landmarks(b)
    assert lm.names == ("P1", "P2") and lm.lps_mm.shape == (2, 3)


def test_landmarks_slicer_markups_ras_and_lps(tmp_path):
    doc = {"markups": [
        {"type": "Fiducial", "coordinateSystem": "RAS",
         "controlPoints": [{"label": "F-1", "position": [10.0, 20.0, 30.0]}]},
        {"type": "Fiducial", "coordinateSystem": "LPS",
         "controlPoints": [{"label": "F-2", "position": [1.0, 2.0, 3.0]}]}]}
    p = tmp_path / "points.mrk.json"
    p.write_text(json.dumps(doc))
    lm = read_landmarks(p)
    assert lm.names == ("F-1", "F-2")
    np.testing.assert_allclose(lm.lps_mm, [[-10.0, -20.0, 30.0], [1.0, 2.0, 3.0]])


@pytest.mark.parametrize("name, text, match", [
    ("bad.csv", "name,x,y,z\na,1,2\n", r"bad\.csv row 1: 'a' is not a number"),
    ("nan.csv", "a,1,nan,3\n", r"nan\.csv row 1: 'nan' must be a finite number"),
    ("word.csv", "a,1,two,3\n", r"word\.csv row 1: 'two' is not a number"),
    ("empty.csv", "x,y,z\n", r"empty\.csv: no landmark in the file"),
    ("x.mrk.json", "{", r"x\.mrk\.json: not a valid JSON file"),
    ("y.mrk.json", "{}", r"y\.mrk\.json: no 'markups' list"),
])
def test_bad_landmark_files(tmp_path, name, text, match):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(TrackingError, match=match):
        read_landmarks(p)
    with pytest.raises(TrackingError, match="file not found"):
        read_landmarks(tmp_path / "missing.csv")


@pytest.mark.parametrize("keep", [False, True])
def test_warped_dicom_series_keeps_the_frame_of_reference(box, labels, tmp_path, keep):
    """``--warp`` of a case whose label map and MR series are DICOM series (issue 55, item
    3): the warped volumes are also written as DICOM series that the project's reader
    reads back with the NIfTI output's voxels and grid, in the source's study and frame of
    reference (new series and instance UIDs), pseudonymised unless ``keep_identifiers``.

    Tolerances: labels are integers and stored as they are (exact); the warped MR values
    (trilinear, float) are stored as 16-bit values with RescaleSlope, so they come back
    within half a step, (max - min) / 65535 / 2; positions are written as DICOM decimal
    strings (16 characters), 1e-4 mm."""
    from types import SimpleNamespace

    import pydicom

    from regtrack.imaging.dicom_series import write_dicom_series
    from regtrack.imaging.readers import read_image_volume, read_label_map
    from regtrack.imaging.volume import ImageVolume
    from regtrack.privacy import dicom_leaks
    from regtrack.tracking.compressed import write_warped

    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in labels.shape], indexing="ij"), -1)
    lps = ijk @ labels.affine[:3, :3].T + labels.affine[:3, 3]
    mr = np.round(500.0 + 3.0 * lps[..., 0] - 2.0 * lps[..., 1] + 1.5 * lps[..., 2]
                  + 40.0 * (labels.data == 2))  # integral, as a scanner's stored values
    src = {"labels": tmp_path / "labels", "series": tmp_path / "series"}
    for vol, folder in ((labels, src["labels"]), (ImageVolume(mr, labels.affine), src["series"])):
        write_dicom_series(vol, folder, patient="JaneDoe1234", transfer_syntax="explicit",
                           deidentify=False, uid_seed=f"test {folder.name}")
    state = SimpleNamespace(case=SimpleNamespace(mri=SimpleNamespace(**src)), view="BIOPSY",
                            dmap=_dmap(box, "rigid")[0])
    out = tmp_path / "out"
    paths = write_warped(out, state, pseudonym="anon-1", keep_identifiers=keep)
    assert {p.parent.name for p in paths if p.suffix == ".dcm"} == {"labels_biopsy", "mri_biopsy"}
    nii_lab = read_label_map(out / "labels_biopsy.nii.gz")
    dcm_lab = read_label_map(out / "labels_biopsy")
    np.testing.assert_array_equal(dcm_lab.data, nii_lab.data)
    np.testing.assert_allclose(dcm_lab.affine, nii_lab.affine, atol=1e-4)
    nii_mr = read_image_volume(out / "mri_biopsy.nii.gz")
    dcm_mr = read_image_volume(out / "mri_biopsy")
    step = float(np.ptp(nii_mr.data)) / 65535
    np.testing.assert_allclose(dcm_mr.data, nii_mr.data, atol=step / 2 + 1e-4)
    np.testing.assert_allclose(dcm_mr.affine, nii_mr.affine, atol=1e-4)
    assert np.ptp(nii_mr.data) > 100  # the warped breast holds the pattern, not background
    for name in ("labels", "series"):
        source = pydicom.dcmread(next(src[name].glob("*.dcm")), stop_before_pixels=True)
        files = sorted((out / f"{'labels' if name == 'labels' else 'mri'}_biopsy").glob("*.dcm"))
        warped = [pydicom.dcmread(f, stop_before_pixels=True) for f in files]
        for ds in warped:
            assert ds.FrameOfReferenceUID == source.FrameOfReferenceUID
            assert ds.StudyInstanceUID == source.StudyInstanceUID
            assert ds.SeriesInstanceUID != source.SeriesInstanceUID
            assert list(ds.ImageOrientationPatient) == pytest.approx(
                list(source.ImageOrientationPatient), abs=1e-6)
            assert list(ds.PixelSpacing) == pytest.approx(list(source.PixelSpacing))
        assert len({ds.SOPInstanceUID for ds in warped}) == len(files)
        assert len({ds.SeriesInstanceUID for ds in warped}) == 1
        if keep:
            assert str(warped[0].PatientName) == "JaneDoe1234"
        else:
            assert str(warped[0].PatientName) == "anon-1"
            assert dicom_leaks(files[0], pseudonym="anon-1") == []
