"""``regtrack mammogram``: case form and file form, outputs (JSON in mm, overlay PNG), errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from regtrack.cli import main
from regtrack.imaging.mammogram.synthetic import synthetic_breast, write_dicom

SP = [0.25, 0.25]


@pytest.fixture
def case_dir(tmp_path):
    """A small valid case: tiny label map, a right CC mammogram without a spacing tag
    (spacing given in case.toml), a tumour polygon and no nipple (detected)."""
    import SimpleITK as sitk

    root = tmp_path / "case"
    (root / "mri").mkdir(parents=True)
    (root / "mammo").mkdir()
    lab = np.zeros((8, 8, 8), np.int16)
    lab[2:6, 2:6, 2:6] = 1
    lab[3:5, 3:5, 3:5] = -3
    lab[0, :, :] = -1
    lab[2, 2, 2:6] = -2
    img = sitk.GetImageFromArray(lab)
    sitk.WriteImage(img, str(root / "mri" / "labels.nii.gz"))
    s = synthetic_breast(tumour_mm=(35.0, 70.0, 6.0))
    stored = s.image[:, ::-1]  # right breast, IHE hanging
    write_dicom(root / "mammo" / "cc.dcm", np.round(stored * 4095), ImageLaterality="R",
                ViewPosition="CC")
    w = stored.shape[1]
    ring = [[70 / 0.25 + 24 * np.sin(t), (w - 1) - (35 / 0.25 + 24 * np.cos(t))]
            for t in np.linspace(0, 2 * np.pi, 24, endpoint=False)]
    (root / "mammo" / "cc_tumour.json").write_text(json.dumps({"points_rc": ring}))
    (root / "case.toml").write_text(
        '[case]\nid = "synth01"\ntitle = "synthetic"\n\n'
        '[mri]\nlabels = "mri/labels.nii.gz"\nscheme = "pelicano-simple"\nside = "R"\n\n'
        '[views.CC]\nmammogram = "mammo/cc.dcm"\ntumour_polygon = "mammo/cc_tumour.json"\n'
        "pixel_spacing_mm = [0.25, 0.25]\n")
    return root, s


def test_case_form_writes_json_in_mm_and_overlay(case_dir, tmp_path):
    root, s = case_dir
    out = tmp_path / "out"
    assert main(["mammogram", str(root), "--view", "cc", "--out", str(out)]) == 0
    doc = json.loads((out / "mammogram_cc.json").read_text())
    assert (out / "mammogram_cc_overlay.png").stat().st_size > 10_000
    assert doc["view"] == "CC" and doc["laterality"] == "R" and doc["case_id"] == "synth01"
    assert np.linalg.norm(np.array(doc["nipple_mm"]) - s.nipple_mm) < 1.0
    t = np.array(doc["tumour_contours_mm"][0])
    np.testing.assert_allclose(t.mean(0), [35.0, 70.0], atol=0.3)
    np.testing.assert_allclose(np.hypot(*(t - [35.0, 70.0]).T), 6.0, atol=1e-6)
    assert doc["meta"]["image"]["spacing_source"] == "user (pixel_spacing_mm)"
    assert len(doc["breast_contour_mm"]) > 100


def test_file_form_and_its_errors(case_dir, tmp_path, capsys):
    root, s = case_dir
    dcm = root / "mammo" / "cc.dcm"
    out = tmp_path / "o2"
    assert main(["mammogram", "--dicom", str(dcm), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cc.dcm: no PixelSpacing or ImagerPixelSpacing tag" in err and "--spacing" in err
    assert not out.exists()
    assert main(["mammogram", "--dicom", str(dcm), "--spacing", "0.25", "0.25", "--out", str(out),
                 "--tumour-seed", "280", "260"]) == 0
    doc = json.loads((out / "mammogram_cc.json").read_text())
    assert doc["meta"]["tumour"]["method"].startswith("seed")
    assert main(["mammogram", "--out", str(out)]) == 2
    assert "give either CASE or --dicom" in capsys.readouterr().err


def test_case_form_unknown_view(case_dir, tmp_path, capsys):
    root, _ = case_dir
    assert main(["mammogram", str(root), "--view", "mlo", "--out", str(tmp_path / "o")]) == 2
    assert "no [views.MLO] section" in capsys.readouterr().err


def test_no_identifier_reaches_the_outputs(tmp_path, caplog, monkeypatch):
    """Issue 53: the JSON held the input's absolute path and the overlay title its file
    name, both of which carry the patient's name here.  The path becomes ``<mammogram>``
    (with the file's SHA-256), the header's name and birth date are redacted wherever
    they occur, and the redaction is announced."""
    import hashlib
    import logging

    import regtrack.imaging.mammogram as mg

    folder = tmp_path / "Doe_Jane_19610304"
    folder.mkdir()
    s = synthetic_breast()
    dcm = write_dicom(folder / "DOE_JANE_cc.dcm", np.round(s.image[:, ::-1] * 4095),
                      ImageLaterality="R", ViewPosition="CC", PixelSpacing=SP,
                      PatientName="Doe^Jane", PatientBirthDate="19610304")
    titles = []
    real = mg.write_overlay
    monkeypatch.setattr(mg, "write_overlay", lambda view, path, **kw:
                        titles.append(kw.get("title")) or real(view, path, **kw))
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="regtrack"):
        assert main(["mammogram", "--dicom", str(dcm), "--out", str(out)]) == 0
    text = (out / "mammogram_cc.json").read_text()
    doc = json.loads(text)
    for leak in ("Doe", "Jane", "19610304", "1961-03-04", folder.name, str(folder)):
        assert leak.lower() not in text.lower(), leak  # (the JSON's floats hold no letters)
        assert all(leak.lower() not in t.lower() for t in titles), (leak, titles)
        assert leak.lower() not in caplog.text.lower(), leak
    assert titles == ["RCC"]
    assert doc["dicom"] == "<mammogram>"
    assert doc["dicom_sha256"] == hashlib.sha256(dcm.read_bytes()).hexdigest()
    assert sorted(p.name for p in out.iterdir()) == ["mammogram_cc.json",
                                                     "mammogram_cc_overlay.png"]

