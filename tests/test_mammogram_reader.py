"""DICOM mammogram reader: tags, decoders, spacing, laterality/view, canonical orientation.

All inputs are small synthetic DICOMs written in ``tmp_path`` with
:func:`regtrack.imaging.mammogram.synthetic.write_dicom`; the canonical image is known,
so every orientation rule is checked by recovering it exactly.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from regtrack.errors import DicomError
from regtrack.imaging.mammogram import mammogram_from_array, read_mammogram
from regtrack.imaging.mammogram.orient import Orientation, parse_patient_orientation
from regtrack.imaging.mammogram.synthetic import synthetic_breast, write_dicom

SP = [0.25, 0.25]


@pytest.fixture(scope="module")
def canon():
    """Canonical synthetic breast as 12-bit integers (chest wall left, label top right)."""
    s = synthetic_breast(shape=(400, 280), yc_mm=50.0, b_mm=40.0, a_mm=45.0)
    return np.round(s.image * 4095).astype(np.uint16)


def _expected(canon):
    return (canon - canon.min()) / float(canon.max() - canon.min())


# stored = transform(canonical); the reader must undo it.  (laterality, view,
# PatientOrientation or None, stored-from-canonical transform)
ORIENTATIONS = [
    ("L", "CC", None, lambda a: a),                        # IHE hanging A\R
    ("R", "CC", None, lambda a: a[:, ::-1]),               # IHE hanging P\L
    ("L", "CC", ["A", "R"], lambda a: a),
    ("R", "CC", ["P", "L"], lambda a: a[:, ::-1]),
    ("R", "CC", ["A", "L"], lambda a: a),                  # right breast already canonical
    ("L", "CC", ["A", "L"], lambda a: a[::-1, :]),         # lateral down: vertical flip
    ("R", "CC", ["P", "R"], lambda a: a[::-1, ::-1]),
    ("L", "MLO", ["A", "FR"], lambda a: a),
    ("R", "MLO", ["P", "FL"], lambda a: a[:, ::-1]),
    ("L", "MLO", ["A", "HR"], lambda a: a[::-1, :]),       # head down: vertical flip
    ("L", "CC", ["R", "A"], lambda a: a.T),                # transposed storage
]


@pytest.mark.parametrize("lat, view, po, stored_from_canon", ORIENTATIONS)
def test_orientation_recovers_canonical_image(tmp_path, canon, lat, view, po, stored_from_canon):
    stored = np.ascontiguousarray(stored_from_canon(canon))
    tags = {"ImageLaterality": lat, "ViewPosition": view, "PixelSpacing": SP}
    if po is not None:
        tags["PatientOrientation"] = po
    img = read_mammogram(write_dicom(tmp_path / "m.dcm", stored, **tags))
    np.testing.assert_allclose(img.image, _expected(canon), atol=1e-6)
    assert (img.laterality, img.view) == (lat, view)
    assert img.meta["orientation"]["rule"].startswith("PatientOrientation" if po else "IHE")
    # a pixel of the stored grid maps onto the same content in the canonical grid
    rng = np.random.default_rng(1)
    rc = rng.integers(0, stored.shape, size=(20, 2))
    crc = img.to_canonical_px(rc).astype(int)
    np.testing.assert_array_equal(img.image[crc[:, 0], crc[:, 1]],
                                  _expected(stored)[rc[:, 0], rc[:, 1]].astype(np.float32))
    np.testing.assert_allclose(img.to_source_px(img.to_canonical_px(rc)), rc)


def test_content_overrides_a_wrong_hanging_and_says_so(tmp_path, canon, caplog):
    # a right breast stored with its chest wall on the left (not the IHE hanging)
    p = write_dicom(tmp_path / "m.dcm", canon, ImageLaterality="R", ViewPosition="CC",
                    PixelSpacing=SP)
    with caplog.at_level(logging.WARNING):
        img = read_mammogram(p)
    np.testing.assert_allclose(img.image, _expected(canon), atol=1e-6)
    assert "left-right flip from image content" in img.meta["orientation"]["rule"]
    assert any("flipped left-right from the image content" in n for n in img.meta["notes"])
    assert "flipped left-right" in caplog.text


def test_laterality_and_view_from_content_when_tags_absent(tmp_path):
    mlo = synthetic_breast(shape=(720, 400), yc_mm=60, b_mm=90, a_mm=70, pectoral_mm=(30, 80))
    stored = np.round(mlo.image[:, ::-1] * 4095)  # right breast, IHE hanging
    img = read_mammogram(write_dicom(tmp_path / "m.dcm", stored, PixelSpacing=SP))
    assert (img.laterality, img.view) == ("R", "MLO")
    assert img.meta["laterality_source"].startswith("image content")
    assert img.meta["view_source"].startswith("image content (pectoral")
    cc = synthetic_breast(shape=(400, 280), yc_mm=50.0, b_mm=40.0, a_mm=45.0)
    img = read_mammogram(write_dicom(tmp_path / "c.dcm", cc.image * 4095, PixelSpacing=SP))
    assert (img.laterality, img.view) == ("L", "CC")


def test_mlo_stored_upside_down_is_flipped_from_content(tmp_path):
    mlo = synthetic_breast(shape=(720, 400), yc_mm=60, b_mm=90, a_mm=70, pectoral_mm=(30, 80))
    canon = np.round(mlo.image * 4095).astype(np.uint16)
    p = write_dicom(tmp_path / "m.dcm", canon[::-1], ImageLaterality="L", ViewPosition="MLO",
                    PixelSpacing=SP)
    img = read_mammogram(p)
    np.testing.assert_allclose(img.image, _expected(canon), atol=1e-6)
    assert img.meta["orientation"]["flip_ud"] is True
    assert img.meta["orientation"]["rule"].endswith("up-down flip from image content")
    # a valid PatientOrientation is trusted on the vertical axis (no content check)
    q = write_dicom(tmp_path / "n.dcm", canon, ImageLaterality="L", ViewPosition="MLO",
                    PixelSpacing=SP, PatientOrientation=["A", "FR"])
    img = read_mammogram(q)
    assert img.meta["orientation"]["flip_ud"] is False
    assert "pectoral_contrast_top_bottom" not in img.meta


def test_cbis_style_view_code_in_patient_orientation(tmp_path, canon):
    p = write_dicom(tmp_path / "m.dcm", canon[:, ::-1], Laterality="R", PatientOrientation="CC",
                    PixelSpacing=SP)
    img = read_mammogram(p)
    assert img.view == "CC" and img.laterality == "R"
    assert img.meta["view_source"].startswith("PatientOrientation (non-standard")
    assert img.meta["laterality_source"] == "Laterality"
    assert img.meta["orientation"]["rule"].startswith("IHE standard hanging")


@pytest.mark.parametrize("tags, expected, source", [
    ({"PixelSpacing": [0.1, 0.12]}, [0.1, 0.12], "PixelSpacing"),
    ({"ImagerPixelSpacing": [0.1, 0.1]}, [0.1, 0.1], "ImagerPixelSpacing"),
    ({"ImagerPixelSpacing": [0.11, 0.11], "EstimatedRadiographicMagnificationFactor": 1.1},
     [0.1, 0.1], "ImagerPixelSpacing / EstimatedRadiographicMagnificationFactor (1.1)"),
    ({"PixelSpacing": [0.1, 0.1], "ImagerPixelSpacing": [0.2, 0.2]}, [0.1, 0.1], "PixelSpacing"),
])
def test_spacing_sources(tmp_path, canon, tags, expected, source):
    img = read_mammogram(write_dicom(tmp_path / "m.dcm", canon, ImageLaterality="L",
                                     ViewPosition="CC", **tags))
    np.testing.assert_allclose(img.pixel_spacing, expected, rtol=1e-12)
    assert img.meta["spacing_source"] == source


def test_user_spacing_and_missing_spacing(tmp_path, canon, caplog):
    p = write_dicom(tmp_path / "nospacing.dcm", canon, ImageLaterality="L", ViewPosition="CC")
    with pytest.raises(DicomError, match=r"nospacing\.dcm: no PixelSpacing or ImagerPixelSpacing "
                       r"tag; give pixel_spacing_mm = \[row, col\]"):
        read_mammogram(p)
    img = read_mammogram(p, pixel_spacing_mm=[0.07, 0.07])
    np.testing.assert_allclose(img.pixel_spacing, [0.07, 0.07])
    assert img.meta["spacing_source"] == "user (pixel_spacing_mm)"
    q = write_dicom(tmp_path / "tagged.dcm", canon, ImageLaterality="L", ViewPosition="CC",
                    PixelSpacing=[0.1, 0.1])
    with caplog.at_level(logging.WARNING):
        img = read_mammogram(q, pixel_spacing_mm=[0.07, 0.07])
    np.testing.assert_allclose(img.pixel_spacing, [0.07, 0.07])
    assert "overrides the DICOM value" in caplog.text
    with pytest.raises(DicomError, match="pixel_spacing_mm .* must be two positive numbers"):
        read_mammogram(p, pixel_spacing_mm=[0.07, -1])


def test_monochrome1_window_and_rle(tmp_path, canon):
    ref = read_mammogram(write_dicom(tmp_path / "a.dcm", canon, ImageLaterality="L",
                                     ViewPosition="CC", PixelSpacing=SP)).image
    inv = read_mammogram(write_dicom(tmp_path / "b.dcm", 4095 - canon, ImageLaterality="L",
                                     ViewPosition="CC", PixelSpacing=SP,
                                     photometric="MONOCHROME1")).image
    np.testing.assert_allclose(inv, ref, atol=1e-6)
    rle = read_mammogram(write_dicom(tmp_path / "c.dcm", canon, ImageLaterality="L",
                                     ViewPosition="CC", PixelSpacing=SP, rle=True))
    np.testing.assert_array_equal(rle.image, ref)
    # a window over the lower half of the range saturates the upper half at 1
    win = read_mammogram(write_dicom(tmp_path / "d.dcm", canon, ImageLaterality="L",
                                     ViewPosition="CC", PixelSpacing=SP, WindowCenter=1024,
                                     WindowWidth=2048))
    assert win.meta["voi"] == "WindowCenter/Width"
    hi = canon > 2100
    assert np.all(win.image[hi] == 1.0)
    lo = (canon > 100) & (canon < 1900)
    # DICOM linear window: y = ((x - (c - 0.5)) / (w - 1) + 0.5), then scaled to [0, 1]
    y = np.clip((canon[lo] - 1023.5) / 2047.0 + 0.5, 0, 1)
    ymin = np.clip((canon.min() - 1023.5) / 2047.0 + 0.5, 0, 1)
    np.testing.assert_allclose(win.image[lo], (y - ymin) / (1 - ymin), atol=1e-5)


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("make, match", [
    (lambda d, a: write_dicom(d / "mr.dcm", a, modality="MR", PixelSpacing=SP),
     r"mr\.dcm: Modality MR is not a mammogram; give a DICOM with Modality MG, DX, CR"),
    (lambda d, a: _write(d / "x.dcm", b"not a dicom at all" * 20),
     r"x\.dcm: not a DICOM file"),
    (lambda d, a: d / "missing.dcm", r"missing\.dcm: file not found"),
    (lambda d, a: write_dicom(d / "rgb.dcm", a, photometric="RGB", PixelSpacing=SP),
     r"rgb\.dcm: PhotometricInterpretation RGB is not supported"),
])
def test_bad_inputs(tmp_path, canon, make, match):
    with pytest.raises(DicomError, match=match):
        read_mammogram(make(tmp_path, canon))


def test_bad_user_view_and_laterality(tmp_path, canon):
    p = write_dicom(tmp_path / "m.dcm", canon, PixelSpacing=SP)
    with pytest.raises(DicomError, match="view 'ML' is not supported; use 'CC' or 'MLO'"):
        read_mammogram(p, view="ML")
    with pytest.raises(DicomError, match="laterality 'B' is not supported"):
        read_mammogram(p, laterality="B")


def test_array_constructor_and_orientation_helpers(canon):
    img = mammogram_from_array(canon[:, ::-1], pixel_spacing_mm=SP, view="CC", laterality="R",
                               source="arr")
    np.testing.assert_allclose(img.image, _expected(canon), atol=1e-6)
    assert parse_patient_orientation("MLO") is None
    assert parse_patient_orientation(["A", "FR"]) == ("A", "FR")
    assert parse_patient_orientation("P\\L") == ("P", "L")
    o = Orientation((10, 20), transpose=True, flip_lr=True, flip_ud=True)
    assert o.shape == (20, 10)
    a = np.arange(200).reshape(10, 20)
    b = o.apply(a)
    rc = np.array([[3, 7], [0, 0], [9, 19]])
    crc = o.to_canonical_px(rc).astype(int)
    np.testing.assert_array_equal(b[crc[:, 0], crc[:, 1]], a[rc[:, 0], rc[:, 1]])
