"""Bad-input corpus through the command line (issue 10, part 1).

Every case starts from the valid synthetic case of ``tests/test_case.py`` (a 14 x 12 x 10
NIfTI label map, two 40 x 30 DICOM MG files, tumour polygons, ``case.toml``; all written
in ``tmp_path``, nothing large is committed) and applies one mutation: the 33 broken
cases of ``test_case.BROKEN`` plus the DICOM, label-map, annotation, TOML and path
mutations below.  Each is run as ``regtrack run CASE --views CC --out OUT --cache CACHE``
through :func:`regtrack.cli.main` from an empty working folder, and must

* exit non-zero (2 for input errors);
* print exactly one ``regtrack run: error: ...`` line on stderr, matching the expected
  text (it names the file and the key/tag and says the fix) and no traceback;
* write nothing: every file under ``tmp_path`` (case folder, working folder, output
  and cache) has the same size and mtime before and after, and OUT/CACHE do not exist.

Warnings (unknown keys, missing laterality tags) are checked for their named text.  A few
cases also go through a real ``python -m regtrack.cli`` subprocess to check the process
exit code and that no traceback reaches the terminal.
"""

from __future__ import annotations

import json
import logging
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from regtrack.cli import main
from tests.test_case import (
    BROKEN,
    COLS,
    ROWS,
    Mutation,
    _set,
    build_case,
    label_data,
    snapshot,
    valid_doc,
    write_dicom,
    write_doc,
    write_labels,
)

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- mutations
def _bytes(rel: str, fn) -> Mutation:
    def mutate(root: Path, doc: dict) -> None:
        p = root / rel
        p.write_bytes(fn(p.read_bytes()))
    return mutate


def _corrupt_middle(data: bytes) -> bytes:
    rng = np.random.default_rng(7)
    b = bytearray(data)
    b[140:400] = rng.integers(0, 256, 260, dtype=np.uint8).tobytes()
    return bytes(b)


def _dicom(**kw) -> Mutation:
    return lambda root, doc: write_dicom(root / "mammo" / "cc.dcm", **kw)


def _dicom_edit(fn) -> Mutation:
    """Rewrite mammo/cc.dcm after ``fn(ds)`` changed its dataset."""
    def mutate(root: Path, doc: dict) -> None:
        import pydicom

        p = root / "mammo" / "cc.dcm"
        ds = pydicom.dcmread(p)
        fn(ds)
        ds.save_as(p)
    return mutate


def _rgb(ds) -> None:
    ds.PhotometricInterpretation = "RGB"
    ds.SamplesPerPixel = 3
    ds.PlanarConfiguration = 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    ds.PixelData = np.zeros((ROWS, COLS, 3), np.uint8).tobytes()


def _constant(ds) -> None:
    ds.PixelData = np.full(ROWS * COLS, 1000, np.uint16).tobytes()


def _multiframe(ds) -> None:
    ds.NumberOfFrames = 2
    ds.PixelData = np.zeros(2 * ROWS * COLS, np.uint16).tobytes()


def _no_rows(ds) -> None:
    del ds.Rows


def _zero_spacing(ds) -> None:
    ds.ImagerPixelSpacing = [0.0, 0.1]


def _labels_fn(fn) -> Mutation:
    return lambda root, doc: write_labels(root / "mri" / "labels.nii.gz", fn(label_data()))


def _nan_labels(d: np.ndarray) -> np.ndarray:
    f = d.astype(np.float32)
    f[3, 3, 3] = np.nan
    return f


def _no_breast(d: np.ndarray) -> np.ndarray:
    d[d > 0] = 0  # tissue labels removed: background, skin, muscle and tumour remain
    return d


def _all_background(d: np.ndarray) -> np.ndarray:
    return np.zeros_like(d)


def _series_of_other_grid(root: Path, doc: dict) -> None:
    from regtrack.imaging.dicom_series import write_dicom_series
    from regtrack.imaging.volume import ImageVolume

    aff = np.diag([1.0, 1.0, 2.0, 1.0])  # 2 mm slices: the label map has 1.5 mm
    aff[:3, 3] = (-10.0, 20.0, 5.0)
    data = np.random.default_rng(0).integers(0, 500, (14, 12, 10)).astype(np.int16)
    write_dicom_series(ImageVolume(data, aff), root / "mri" / "dicom", transfer_syntax="explicit")
    doc["mri"]["series"] = "mri/dicom"


def _series_link_outside(root: Path, doc: dict) -> None:
    (root.parent / "other_series").mkdir()
    (root / "mri" / "dicom").symlink_to(root.parent / "other_series", target_is_directory=True)
    doc["mri"]["series"] = "mri/dicom"


def _write(rel: str, text: str) -> Mutation:
    return lambda root, doc: (root / rel).write_text(text)


def _raw_toml(text: str | bytes) -> Mutation:
    """Replace case.toml after the document is written (the runner writes ``doc`` first)."""
    def mutate(root: Path, doc: dict) -> None:
        doc["__raw__"] = text
    return mutate


def _empty_mask(root: Path, doc: dict) -> None:
    import cv2

    cv2.imwrite(str(root / "mammo" / "cc_mask.png"), np.zeros((ROWS, COLS), np.uint8))
    del doc["views"]["CC"]["tumour_polygon"]
    doc["views"]["CC"]["tumour_mask"] = "mammo/cc_mask.png"


def _only_mlo_view(root: Path, doc: dict) -> None:
    del doc["views"]["CC"]


def _truncate(rel: str, fraction: float) -> Mutation:
    """Keep the first ``fraction`` of a file (issue 53: a .nii.gz cut at 60-99.5 % was read
    zero-filled, a 7.3 mL tumour becoming 1.9 mL)."""
    return _bytes(rel, lambda b: b[: int(len(b) * fraction)])


def _labels_uncompressed_truncated(root: Path, doc: dict) -> None:
    """An uncompressed .nii short of its header's voxel count by 40 bytes."""
    p = root / "mri" / "labels.nii"
    write_labels(p, label_data())
    p.write_bytes(p.read_bytes()[:-40])
    doc["mri"]["labels"] = "mri/labels.nii"


def _labels_regzipped_short(root: Path, doc: dict) -> None:
    """A complete gzip stream around a NIfTI whose voxel data are cut short."""
    import gzip

    p = root / "mri" / "labels.nii.gz"
    raw = gzip.decompress(p.read_bytes())
    p.write_bytes(gzip.compress(raw[:-200]))


def _labels_crc(root: Path, doc: dict) -> None:
    """One flipped byte in the middle of the deflate stream: the gzip CRC check fails."""
    p = root / "mri" / "labels.nii.gz"
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 0xFF
    p.write_bytes(bytes(b))


def _huge_size_claim(ds) -> None:
    ds.Rows, ds.Columns = 65535, 65535


def _jpeg_12bit(root: Path, doc: dict) -> None:
    """pydicom's 12-bit JPEG Extended test file as the CC mammogram: Pillow cannot decode
    12-bit JPEG, pylibjpeg-libjpeg refuses this stream, GDCM (not installed) would."""
    import pydicom
    from pydicom.data import get_testdata_file

    ds = pydicom.dcmread(get_testdata_file("JPEG-lossy.dcm"))
    ds.Modality, ds.ImageLaterality, ds.ViewPosition = "MG", "R", "CC"
    ds.save_as(root / "mammo" / "cc.dcm")


EXTRA: list[tuple[str, Mutation, str]] = [
    # --- DICOM mammograms
    ("truncated DICOM header", _bytes("mammo/cc.dcm", lambda b: b[:200]),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': (cannot read the DICOM header .*truncated"
     r"|DICOM tag Rows/Columns missing)"),
    ("truncated pixel data", _bytes("mammo/cc.dcm", lambda b: b[: len(b) - ROWS * COLS]),
     r"cc\.dcm: cannot decode the pixel data: PixelData holds 1200 bytes but Rows x Columns x "
     r"BitsAllocated \(40 x 30 x 16\) need 2400; the file is truncated or those tags are wrong"),
    ("zero-byte DICOM", _bytes("mammo/cc.dcm", lambda b: b""),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': (not a DICOM file|cannot read the DICOM "
     r"header)"),
    ("corrupt DICOM header bytes", _bytes("mammo/cc.dcm", _corrupt_middle),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': (cannot read the DICOM header|DICOM tag "
     r"Rows/Columns missing|not a DICOM file)"),
    ("wrong modality (MR)", _dicom(modality="MR"),
     r"cc\.dcm: Modality MR is not a mammogram; give a DICOM with Modality MG, DX, CR"),
    ("RGB pixels", _dicom_edit(_rgb),
     r"cc\.dcm: (PhotometricInterpretation RGB is not supported|pixel data has shape)"),
    ("constant pixels", _dicom_edit(_constant),
     r"cc\.dcm: pixel data are constant \(1000\); not an image"),
    ("multi-frame", _dicom_edit(_multiframe),
     r"cc\.dcm: pixel data has shape \(2, 40, 30\); a single-frame grey-level mammogram"),
    ("no Rows tag", _dicom_edit(_no_rows),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': DICOM tag Rows/Columns missing"),
    ("zero pixel spacing", _dicom_edit(_zero_spacing),
     r"\[views\.CC\] mammogram = 'mammo/cc\.dcm': spacing missing"),
    # --- label maps and MRI series
    ("NaN in the label map", _labels_fn(_nan_labels),
     r"\[mri\] labels = 'mri/labels\.nii\.gz': .*(NaN|non-finite|not finite|non-integer)"),
    ("label map without breast tissue", _labels_fn(_no_breast),
     r"\[mri\.label_values\] tissue = \[1, 2, 3, 4, 5, 6, 7\]: no voxel of "
     r"'mri/labels\.nii\.gz' has these values"),
    ("empty label map", _labels_fn(_all_background),
     r"2 problems:\n  - .*\[mri\.label_values\] tissue = .*: no voxel of 'mri/labels\.nii\.gz'.*"
     r"\n  - .*\[mri\.label_values\] tumour = \[-3, -4\]: no voxel"),
    ("MRI series on another grid", _series_of_other_grid,
     r"\[mri\] series = 'mri/dicom': voxel grid is .* mm away from the label map's"),
    ("series folder linked outside", _series_link_outside,
     r"\[mri\] series = 'mri/dicom': resolves to .*other_series, outside the case folder"),
    ("series path climbing out", _set("mri", "series", "../"),
     r"\[mri\] series = '\.\./': the path leaves the case folder"),
    ("home-relative path", _set("views.CC", "mammogram", "~/cc.dcm"),
     r"\[views\.CC\] mammogram = '~/cc\.dcm': absolute paths are not allowed"),
    ("Windows absolute path", _set("views.CC", "mammogram", "C:\\scans\\cc.dcm"),
     r"absolute paths are not allowed"),
    # --- annotations
    ("self-intersecting tumour polygon",
     _write("mammo/cc_tumour.json", '{"points_rc": [[10, 10], [14, 14], [10, 14], [15, 10]]}'),
     r"\[views\.CC\] tumour_polygon = 'mammo/cc_tumour\.json': points_rc is not a simple "
     r"polygon"),
    ("tumour polygon with NaN",
     _write("mammo/cc_tumour.json", '{"points_rc": [[10, 10], [NaN, 14], [14, 10]]}'),
     r"\[views\.CC\] tumour_polygon = 'mammo/cc_tumour\.json': .*(finite|NaN|number)"),
    ("tumour polygon under the wrong key",
     _write("mammo/cc_tumour.json", '{"points": [[10, 10], [10, 14], [14, 10]]}'),
     r"\[views\.CC\] tumour_polygon = 'mammo/cc_tumour\.json': .*points_rc"),
    ("empty tumour mask", _empty_mask,
     r"\[views\.CC\] tumour_mask = 'mammo/cc_mask\.png': .*(empty|no tumour|no pixel)"),
    # --- case.toml types and values
    ("string where a list is expected", _set("views.CC", "nipple_px", "20, 28"),
     r"\[views\.CC\] nipple_px = '20, 28': expected tuple\[float, \.\.\.\]"),
    ("string where a number is expected", _set("model", "target_nodes", "many"),
     r"\[model\] target_nodes = 'many': expected int"),
    ("number as case id", _set("case", "id", 5),
     r"\[case\] id = 5: expected str"),
    ("view given as a string", _set("views", "CC", "mammo/cc.dcm"),
     r"\[views\] CC = 'mammo/cc\.dcm': expected a table \[views\.CC\]"),
    ("NaN Poisson ratio", _set("mechanics", "nu", float("nan")),
     r"\[mechanics\] nu = nan: must be >= 0\.0 \(Poisson's ratio"),
    ("infinite stiffness", _set("mechanics", "tissue_c1_kpa", float("inf")),
     r"\[mechanics\] tissue_c1_kpa = inf kPa: must be <= 10000\.0"),
    ("NaN nipple coordinate", _set("mri", "nipple_lps_mm", [float("nan"), 26.0, 15.0]),
     r"\[mri\] nipple_lps_mm = \[nan, 26\.0, 15\.0\]: outside 'mri/labels\.nii\.gz'"),
    ("negative pixel spacing", _set("views.CC", "pixel_spacing_mm", [-0.1, 0.1]),
     r"\[views\.CC\]: pixel_spacing_mm = \[-0\.1, 0\.1\]: .*(> 0|positive)"),
    ("empty case.toml", _raw_toml(""),
     r"2 problems:\n  - .*\[case\]: missing section; add a \[case\] table.*\n  - .*\[mri\]: "
     r"missing section"),
    ("invalid TOML", _raw_toml('[case]\nid = "x"\n[mri\n'), r"invalid TOML: .*line 3"),
    ("case.toml not UTF-8", _raw_toml(b'[case]\nid = "caf\xe9"\n'), r"not UTF-8 text"),
    ("requested view absent", _only_mlo_view,
     r"view\(s\) CC requested but the case has MLO; add \[views\.CC\]"),
    # --- issue 53: truncated label maps, impossible DICOM sizes, undecodable JPEG
    ("label map cut at 60 %", _truncate("mri/labels.nii.gz", 0.60),
     r"\[mri\] labels = 'mri/labels\.nii\.gz': the gzip stream is truncated or corrupt "
     r"\(Compressed file ended before the end-of-stream marker was reached\); the file is "
     r"incomplete: copy or export it again"),
    ("label map cut at 99.5 %", _truncate("mri/labels.nii.gz", 0.995),
     r"\[mri\] labels = 'mri/labels\.nii\.gz': the gzip stream is truncated or corrupt"),
    ("label map .nii 40 bytes short", _labels_uncompressed_truncated,
     r"\[mri\] labels = 'mri/labels\.nii': the file holds 3672 bytes but its header "
     r"\(14x12x10 voxels of int16\) needs 3712; the file is truncated"),
    ("label map re-gzipped short", _labels_regzipped_short,
     r"\[mri\] labels = 'mri/labels\.nii\.gz': the file holds 3512 bytes but its header "
     r"\(14x12x10 voxels of int16\) needs 3712; the file is truncated"),
    ("label map gzip CRC error", _labels_crc,
     r"\[mri\] labels = 'mri/labels\.nii\.gz': the gzip stream is truncated or corrupt "
     r"\((CRC check failed|Error -3 while decompressing)"),
    ("65535 x 65535 size claim", _dicom_edit(_huge_size_claim),
     r"cc\.dcm: cannot decode the pixel data: Rows x Columns 65535 x 65535 \(4\.3e\+09 "
     r"pixels, 8\.0 GiB\) is larger than any mammogram; the header is corrupt"),
    ("12-bit JPEG Extended", _jpeg_12bit,
     r"cc\.dcm: cannot decode the pixel data \(transfer syntax JPEG Extended \(Process 2 "
     r"and 4\), 12-bit\): the installed decoders \(.*pylibjpeg.*\) failed \(.*Pillow does "
     r"not support.*12-bit.*\); not installed: gdcm \(pip install python-gdcm\)"),
]

CORPUS = [(f"case:{n}", m, e) for n, m, e in BROKEN] + EXTRA


def _apply(case_dir: Path, mutate: Mutation) -> None:
    doc = valid_doc()
    mutate(case_dir, doc)
    raw = doc.pop("__raw__", None)
    write_doc(case_dir, doc)
    if raw is not None:
        p = case_dir / "case.toml"
        p.write_bytes(raw if isinstance(raw, bytes) else raw.encode())


def _error_lines(err: str) -> list[str]:
    """The error line(s) on stderr; a :class:`CaseError` listing several problems keeps its
    ``  - problem`` lines attached to its one error line."""
    out: list[str] = []
    for ln in err.splitlines():
        if ln.startswith("regtrack run: error:"):
            out.append(ln)
        elif ln.startswith("  - ") and out:
            out[-1] += "\n" + ln
    return out


def test_corpus_is_large_enough() -> None:
    """Issue 53: at least 60 bad inputs, each with its expected one-line message."""
    assert len(CORPUS) + len(ARGS) >= 60 + 40
    assert all(message for _, _, message in CORPUS + ARGS)


@pytest.mark.parametrize("name, mutate, message", CORPUS, ids=[c[0] for c in CORPUS])
def test_bad_input_gives_one_error_and_writes_nothing(tmp_path: Path, name: str, mutate: Mutation,
                                                      message: str, capsys, monkeypatch) -> None:
    case_dir = build_case(tmp_path / "synth01")
    _apply(case_dir, mutate)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    before = snapshot(tmp_path)
    capsys.readouterr()
    rc = main(["-q", "run", str(case_dir), "--views", "CC", "--out", str(work / "out"),
               "--cache", str(work / "cache")])
    err = capsys.readouterr().err
    assert rc == 2, (rc, err)
    assert "Traceback" not in err
    lines = _error_lines(err)
    assert len(lines) == 1, err
    assert re.search(message, lines[0]), lines[0]
    assert snapshot(tmp_path) == before  # nothing written, nothing touched
    assert not (work / "out").exists() and not (work / "cache").exists()


def test_unknown_keys_are_named_warnings_with_the_closest_key(tmp_path: Path, capsys) -> None:
    case_dir = build_case(tmp_path / "synth01")
    doc = valid_doc()
    doc["mechanics"]["tissue_c1_kap"] = 0.6
    doc["regstration"] = {"bracket_deg": 20}
    write_doc(case_dir, doc)
    before = snapshot(tmp_path)
    assert main(["validate", str(case_dir)]) == 0
    out = capsys.readouterr().out
    assert "unknown key 'tissue_c1_kap' ignored (did you mean 'tissue_c1_kpa'?)" in out
    assert "unknown section or key 'regstration' ignored (did you mean 'registration'?)" in out
    assert snapshot(tmp_path) == before


def test_missing_laterality_and_orientation_tags_are_named_warnings(tmp_path: Path,
                                                                    caplog) -> None:
    """Without ImageLaterality/Laterality/PatientOrientation/ViewPosition the reader decides
    from the image content and says so, naming the tag (a warning, not a silent guess)."""
    from regtrack.imaging.mammogram import read_mammogram
    from regtrack.imaging.mammogram.synthetic import synthetic_breast
    from regtrack.imaging.mammogram.synthetic import write_dicom as write_mg

    sb = synthetic_breast(shape=(300, 200), spacing=(0.5, 0.5), a_mm=60, b_mm=50, yc_mm=75,
                          label=False, film_edge_mm=0)
    p = write_mg(tmp_path / "bare.dcm", sb.image[:, ::-1] * 4000, PixelSpacing=[0.5, 0.5])
    with caplog.at_level(logging.WARNING, logger="regtrack"):
        img = read_mammogram(p)
    text = caplog.text
    assert "no ImageLaterality/Laterality tag; laterality R from the image content" in text
    assert "no ViewPosition tag; view CC from the image content" in text
    assert img.laterality == "R" and img.view == "CC"
    assert any("ImageLaterality" in n for n in img.meta["notes"])  # recorded, not only logged


def test_monochrome1_is_read_inverted(tmp_path: Path) -> None:
    """MONOCHROME1 (bright = low value) gives the same canonical image as MONOCHROME2."""
    from regtrack.imaging.mammogram import read_mammogram
    from regtrack.imaging.mammogram.synthetic import synthetic_breast
    from regtrack.imaging.mammogram.synthetic import write_dicom as write_mg

    sb = synthetic_breast(shape=(300, 200), spacing=(0.5, 0.5), label=False, film_edge_mm=0)
    px = np.round(sb.image * 4000)
    tags = dict(PixelSpacing=[0.5, 0.5], ImageLaterality="L", ViewPosition="CC")
    a = read_mammogram(write_mg(tmp_path / "m2.dcm", px, **tags))
    b = read_mammogram(write_mg(tmp_path / "m1.dcm", 4000 - px, photometric="MONOCHROME1", **tags))
    np.testing.assert_allclose(a.image, b.image, atol=1e-6)  # float32 rounding only


SUBPROCESS = ["case:path escaping with ..", "truncated pixel data", "invalid TOML"]


@pytest.mark.parametrize("name", SUBPROCESS)
def test_bad_input_in_a_real_process(tmp_path: Path, name: str) -> None:
    """The installed entry point: exit status 2, one error line, no traceback."""
    _, mutate, message = next(c for c in CORPUS if c[0] == name)
    case_dir = build_case(tmp_path / "synth01")
    _apply(case_dir, mutate)
    work = tmp_path / "work"
    work.mkdir()
    before = snapshot(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "regtrack.cli", "run", str(case_dir),
                           "--views", "CC", "--out", "out", "--cache", "cache"],
                          cwd=work, capture_output=True, text=True,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    lines = _error_lines(proc.stderr)
    assert len(lines) == 1 and re.search(message, lines[0]), proc.stderr
    assert snapshot(tmp_path) == before


def test_corpus_names_are_unique() -> None:
    names = [c[0] for c in CORPUS + ARGS]
    assert len(set(names)) == len(names)


# ----------------------------------------------------------------------------- guard rails
def _box():
    from regtrack.mechanics.meshes import box_model

    return box_model((10.0, 10.0, 10.0), (2, 2, 2))


def _doc(**summary) -> dict:
    base = {"complete": True, "D": 0.4, "max_penetration_mm": 0.01}
    return {"summary": {**base, **summary}, "steps": [{"max_penetration_mm": 0.01}],
            "error": None}


@pytest.mark.parametrize("case, message", [
    ("incomplete", r"simulate CC: the protocol did not complete \(converged flag false\)"),
    ("error", r"simulate CC: the solver reported an error \(diverged at step 2\)"),
    ("nan", r"simulate CC: 1 node position\(s\) are not finite"),
    ("inverted", r"simulate CC: \d+ of 48 element\(s\) inverted or collapsed"),
    ("penetration", r"simulate CC: plate penetration 0\.5 mm exceeds \[contact\] "
                    r"max_penetration_mm = 0\.1 mm"),
    ("D", r"simulate CC: compression degree D = 1\.2 is outside \[0, 1\)"),
    ("shape", r"simulate CC: \(26, 3\) deformed positions for a model of 27 nodes"),
])
def test_simulation_guard_rails(case: str, message: str) -> None:
    """Each check on its own: a result that breaks it is an error naming the stage."""
    from regtrack.errors import ResultCheckError
    from regtrack.pipeline.guards import check_simulation

    model = _box()
    x = model.points * np.array([1.0, 1.0, 0.6])  # a valid 40 % compression
    doc = _doc()
    check_simulation("simulate CC", doc, x, model, max_penetration_mm=0.1)  # valid: passes
    if case == "incomplete":
        doc = _doc(complete=False)
    elif case == "error":
        doc = {**doc, "error": "diverged at step 2"}
    elif case == "nan":
        x = x.copy()
        x[5, 1] = np.nan
    elif case == "inverted":
        x = x.copy()
        x[:, 2] = -x[:, 2]  # mirror: every element turned inside out
    elif case == "penetration":
        doc["steps"][0]["max_penetration_mm"] = 0.5
    elif case == "D":
        doc = _doc(D=1.2)
    elif case == "shape":
        x = x[:-1]
    with pytest.raises(ResultCheckError, match=message) as info:
        check_simulation("simulate CC", doc, x, model, max_penetration_mm=0.1)
    assert info.value.exit_code == 3 and "\n" not in str(info.value)


def test_metrics_guard_rail() -> None:
    from regtrack.errors import ResultCheckError
    from regtrack.pipeline.guards import check_metrics_row

    row = {"BS_Av": 90.0, "theta_p_b": 1.0, "theta_p": 1.5, "d_B": 2.0, "TS_Av": None}
    check_metrics_row("register CC", row)
    with pytest.raises(ResultCheckError, match=r"register CC: TS_Av = nan is not finite"):
        check_metrics_row("register CC", {**row, "TS_Av": float("nan")})
    with pytest.raises(ResultCheckError, match=r"register CC: BS_Av could not be computed"):
        check_metrics_row("register CC", {**row, "BS_Av": None})


def test_failed_simulation_check_is_never_cached(tmp_path: Path, monkeypatch) -> None:
    """simulate_stage runs the guard inside the cache's temporary folder: a diverged
    result raises ResultCheckError naming the stage and leaves no stage folder."""
    import meshio

    import regtrack.mechanics.run_view as run_view
    from regtrack.errors import ResultCheckError
    from regtrack.pipeline import stages
    from regtrack.pipeline.run import open_run

    case_dir = build_case(tmp_path / "synth01")
    from regtrack.case import load_case, resolve_configs

    case = load_case(case_dir)
    ctx = open_run(case, resolve_configs(case), cache_dir=tmp_path / "cache")
    model = _box()

    def diverged(case, model, view, *, out_dir, **kw):
        u = np.zeros_like(model.points)
        u[3] = np.nan
        meshio.write(out_dir / "x.vtu", meshio.Mesh(model.points, [("tetra", model.tets)],
                                                    point_data={"displacement": u}))
        (out_dir / "x.json").write_text(json.dumps(_doc()))

    monkeypatch.setattr(run_view, "simulate_view", diverged)
    mesh = stages.MeshOutput("k", tmp_path, model)
    with pytest.raises(ResultCheckError, match=r"^simulate CC: .*non-finite values"):
        stages.simulate_stage(ctx, mesh, "CC")
    folder = tmp_path / "cache" / "simulate"
    assert [d.name for d in folder.iterdir()] == []  # nothing cached, no temporary left


# ----------------------------------------------------------------------------- command line
# Bad options of every command (issue 53): each is refused with one line before any work
# (no mesh, simulation or registration starts: the track cases pass --no-simulate so that
# a check that let them through would fail at once instead of meshing), nothing written.
def _jpeg12_file(work: Path) -> Path:
    import pydicom
    from pydicom.data import get_testdata_file

    ds = pydicom.dcmread(get_testdata_file("JPEG-lossy.dcm"))
    ds.Modality, ds.ImageLaterality, ds.ViewPosition = "MG", "R", "CC"
    ds.save_as(work / "jpeg12.dcm")
    return work / "jpeg12.dcm"


def _huge_file(work: Path) -> Path:
    import pydicom

    write_dicom(work / "ok.dcm", view="CC")
    ds = pydicom.dcmread(work / "ok.dcm")
    ds.Rows, ds.Columns = 65535, 65535
    ds.save_as(work / "huge.dcm")
    return work / "huge.dcm"


def _study_file(work: Path, runner: str) -> Path:
    p = work / "s.toml"
    p.write_text(f'[study]\nrunner = "{runner}"\n[cases]\npaths = ["../synth01"]\n')
    return p


def _file(work: Path, name: str = "afile") -> Path:
    (work / name).write_text("not a folder")
    return work / name


#: (name, argv(case, work) -> list, expected one-line message)
ARGS: list[tuple[str, Callable[[Path, Path], list[str]], str]] = [
    # --- regtrack run: --set checked against the schema, folders checked first
    ("run --set misspelt key", lambda c, w: ["run", str(c), "--set", "model.target_nodez=3000"],
     r"^regtrack run: error: --set model\.target_nodez=3000: unknown key 'target_nodez' in "
     r"\[model\] \(did you mean 'target_nodes'\?\)$"),
    ("run --set unknown section", lambda c, w: ["run", str(c), "--set", "bogus.key=1"],
     r"^regtrack run: error: --set bogus\.key=1: unknown section 'bogus'; sections: model, "
     r"mechanics, contact, protocol\.CC, protocol\.MLO, protocol\.BIOPSY, registration, "
     r"virtual, tracking$"),
    ("run --set misspelt section", lambda c, w: ["run", str(c), "--set", "mechanic.nu=0.4"],
     r"--set mechanic\.nu=0\.4: unknown section 'mechanic' \(did you mean 'mechanics'\?\)"),
    ("run --set unknown view", lambda c, w: ["run", str(c), "--set", "protocol.ML.target_D=0.3"],
     r"--set protocol\.ML\.target_D=0\.3: unknown section 'protocol\.ML' \(did you mean "
     r"'protocol\.(MLO|CC)'\?\)"),
    ("run --set nested misspelt key",
     lambda c, w: ["run", str(c), "--set", "mechanics.solver.max_iteratons=30"],
     r"--set mechanics\.solver\.max_iteratons=30: unknown key 'max_iteratons' in "
     r"\[mechanics\.solver\] \(did you mean 'max_iterations'\?\)"),
    ("run --set option of the removed Newton solver",
     lambda c, w: ["run", str(c), "--set", "mechanics.solver.stabilisation=off"],
     r"--set mechanics\.solver\.stabilisation=off: unknown key 'stabilisation' in "
     r"\[mechanics\.solver\]"),
    ("run --set value out of range", lambda c, w: ["run", str(c), "--set", "model.target_nodes=5"],
     r"--set model\.target_nodes=5: \[model\] target_nodes = 5 nodes: must be >= 200"),
    ("run --set wrong type", lambda c, w: ["run", str(c), "--set", "mechanics.nu=soft"],
     r"--set mechanics\.nu=soft: \[mechanics\] nu = 'soft': expected float"),
    ("run --set without a value", lambda c, w: ["run", str(c), "--set", "model.target_nodes"],
     r"--set 'model\.target_nodes': expected SECTION\.KEY=VALUE"),
    ("run --set section only", lambda c, w: ["run", str(c), "--set", "virtual=1"],
     r"--set 'virtual=1': expected SECTION\.KEY=VALUE"),
    ("run --out names a file", lambda c, w: ["run", str(c), "--out", str(_file(w))],
     r"^regtrack run: error: --out .*afile: is a file, not a folder; give a folder path"),
    ("run --cache names a file", lambda c, w: ["run", str(c), "--cache", str(_file(w))],
     r"^regtrack run: error: --cache .*afile: is a file, not a folder"),
    ("run --out below a file", lambda c, w: ["run", str(c), "--out", str(_file(w) / "sub")],
     r"--out .*afile/sub: .*afile is a file, so the folder cannot be created"),
    ("run unknown view", lambda c, w: ["run", str(c), "--views", "CC,AP"],
     r"--views: unknown view .AP.; use CC and/or MLO"),
    # --- regtrack mesh: numbers range-checked before meshing
    ("mesh --element-size -1",
     lambda c, w: ["mesh", "--labels", str(c / "mri/labels.nii.gz"), "--element-size", "-1"],
     r"^regtrack mesh: error: --element-size -1: must be > 0\.3 mm and <= 50 mm "
     r"\(tetrahedron edge length\)$"),
    ("mesh --element-size 0",
     lambda c, w: ["mesh", "--labels", str(c / "mri/labels.nii.gz"), "--element-size", "0"],
     r"--element-size 0: must be > 0\.3 mm"),
    ("mesh --element-size nan",
     lambda c, w: ["mesh", "--labels", str(c / "mri/labels.nii.gz"), "--element-size", "nan"],
     r"--element-size nan: must be > 0\.3 mm and <= 50 mm"),
    ("mesh --element-size 500",
     lambda c, w: ["mesh", "--labels", str(c / "mri/labels.nii.gz"), "--element-size", "500"],
     r"--element-size 500: must be > 0\.3 mm and <= 50 mm"),
    ("mesh --target-nodes 5",
     lambda c, w: ["mesh", "--labels", str(c / "mri/labels.nii.gz"), "--target-nodes", "5"],
     r"^regtrack mesh: error: --target-nodes 5: must be >= 200 and <= 2e\+06 \(approximate "
     r"node count of the mesh\)$"),
    ("mesh --target-nodes 0",
     lambda c, w: ["mesh", str(c), "--target-nodes", "0"], r"--target-nodes 0: must be >= 200"),
    ("mesh --labels missing", lambda c, w: ["mesh", "--labels", str(w / "nope.nii.gz")],
     r"--labels .*nope\.nii\.gz: label map not found; check the path"),
    ("mesh truncated --labels",
     lambda c, w: ["mesh", "--labels", str(_cut(c / "mri/labels.nii.gz", w, 0.8)),
                   "--out", str(w / "m")],
     r"cut\.nii\.gz: the gzip stream is truncated or corrupt"),
    ("mesh --out names a file",
     lambda c, w: ["mesh", "--labels", str(c / "mri/labels.nii.gz"), "--out", str(_file(w))],
     r"--out .*afile: is a file, not a folder"),
    # --- regtrack track: inputs checked before the mesh, simulations and registration
    ("track --cc-contour missing",
     lambda c, w: ["track", str(c), "--cc-contour", str(w / "missing.json"), "--no-simulate"],
     r"^regtrack track: error: --cc-contour .*missing\.json: contour JSON not found; check "
     r"the path$"),
    ("track --mlo-contour is a folder",
     lambda c, w: ["track", str(c), "--mlo-contour", str(w), "--no-simulate"],
     r"--mlo-contour .*: is a folder; give the contour JSON file"),
    ("track --cc-contour invalid JSON",
     lambda c, w: ["track", str(c), "--cc-contour", str(_file(w, "c.json")), "--no-simulate"],
     r"c\.json: invalid JSON"),
    ("track --cc-point off the image",
     lambda c, w: ["track", str(c), "--cc-point", "400", "10", "--no-simulate"],
     r"--cc-point: \(row 400, col 10\) is outside the CC mammogram \(40 rows x 30 columns\)"),
    ("track --mlo-point negative",
     lambda c, w: ["track", str(c), "--mlo-point", "-5", "10", "--no-simulate"],
     r"--mlo-point: \(row -5, col 10\) is outside the MLO mammogram"),
    ("track --cc-contour off the image",
     lambda c, w: ["track", str(c), "--cc-contour", str(_poly(w, [[10, 10], [10, 90], [15, 50]])),
                   "--no-simulate"],
     r"--cc-contour: \(row 10, col 90\) is outside the CC mammogram \(40 rows x 30 columns\)"),
    ("track --cc-point NaN",
     lambda c, w: ["track", str(c), "--cc-point", "nan", "3", "--no-simulate"],
     r"--cc-point nan 3\.0: coordinates must be finite numbers"),
    ("track --mri-point inf",
     lambda c, w: ["track", str(c), "--mri-point", "0", "inf", "0", "--no-simulate"],
     r"--mri-point 0\.0 inf 0\.0: coordinates must be finite numbers"),
    ("track nothing to track", lambda c, w: ["track", str(c), "--no-simulate"],
     r"nothing to track: give --mri-point, --label, --cc-point, --mlo-point, --cc-contour or "
     r"--mlo-contour"),
    ("track --mri-point and --label",
     lambda c, w: ["track", str(c), "--mri-point", "0", "0", "0", "--label", "tumour"],
     r"give either --mri-point or --label, not both"),
    ("track --cc-point with one view",
     lambda c, w: ["track", str(c), "--cc-point", "5", "5", "--views", "CC", "--no-simulate"],
     r"--cc-point needs both CC and MLO in --views"),
    ("track unknown view",
     lambda c, w: ["track", str(c), "--label", "tumour", "--views", "CC,AP", "--no-simulate"],
     r"--views: unknown view 'AP'; use CC and/or MLO"),
    ("track --label absent value",
     lambda c, w: ["track", str(c), "--label", "42", "--no-simulate"],
     r"--label 42: label value 42 is not in the label map \(values present: .*\); choose "
     r"--label from those, or 'tumour'"),
    ("track --label bad syntax",
     lambda c, w: ["track", str(c), "--label", "tumour:0", "--no-simulate"],
     r"--label 'tumour:0': use 'tumour' \(every tumour of the model\), 'tumour:K'"),
    ("track --ray-step 0",
     lambda c, w: ["track", str(c), "--cc-point", "5", "5", "--ray-step", "0"],
     r"--ray-step 0\.0: must be in \(0, 5\] mm"),
    ("track --cache names a file",
     lambda c, w: ["track", str(c), "--label", "tumour", "--cache", str(_file(w))],
     r"--cache .*afile: is a file, not a folder"),
    # --- regtrack mammogram: decoder advice, sizes, options
    ("mammogram 12-bit JPEG Extended",
     lambda c, w: ["mammogram", "--dicom", str(_jpeg12_file(w)), "--out", str(w / "o")],
     r"jpeg12\.dcm: cannot decode the pixel data \(transfer syntax JPEG Extended \(Process 2 "
     r"and 4\), 12-bit\): the installed decoders \(.*\) failed .*; not installed: gdcm \(pip "
     r"install python-gdcm\); install one of them or re-export the image uncompressed$"),
    ("mammogram 65535 x 65535",
     lambda c, w: ["mammogram", "--dicom", str(_huge_file(w)), "--out", str(w / "o")],
     r"huge\.dcm: cannot decode the pixel data: Rows x Columns 65535 x 65535 .* is larger "
     r"than any mammogram"),
    ("mammogram --spacing -0.1",
     lambda c, w: ["mammogram", str(c), "--view", "cc", "--spacing", "-0.1", "0.1"],
     r"--spacing -0\.1: must be > 0 mm and <= 10 mm \(pixel spacing \(row, col\)\)"),
    ("mammogram --nipple negative",
     lambda c, w: ["mammogram", str(c), "--view", "cc", "--nipple", "-3", "4"],
     r"--nipple -3: must be >= 0"),
    ("mammogram --out names a file",
     lambda c, w: ["mammogram", str(c), "--view", "cc", "--out", str(_file(w))],
     r"--out .*afile: is a file, not a folder"),
    ("mammogram missing --dicom",
     lambda c, w: ["mammogram", "--dicom", str(w / "none.dcm"), "--out", str(w / "o")],
     r"^regtrack mammogram: error: --dicom .*none\.dcm: DICOM mammogram not found; check "
     r"the path$"),
    # --- regtrack simulate / project
    ("simulate --model missing",
     lambda c, w: ["simulate", "--model", str(w / "m.vtu"), "--config", "c.toml", "--out", "r.vtu"],
     r"^regtrack simulate: error: --model .*m\.vtu: model \.vtu not found; check the path$"),
    ("simulate --out below a file",
     lambda c, w: ["simulate", "--model", str(_file(w, "m.vtu")), "--config", "c.toml",
                   "--out", str(_file(w) / "r.vtu")],
     r"--out .*afile: is a file, not a folder"),
    ("project --out names a file",
     lambda c, w: ["project", "--model", "m.vtu", "--result", "r.vtu", "--view", "CC", "--out",
                   str(_file(w))],
     r"^regtrack project: error: --out .*afile: is a file, not a folder"),
    # --- regtrack study / calibrate: a data file names a runner, never code
    ("study runner import path", lambda c, w: ["study", str(_study_file(w, "this:s"))],
     r"s\.toml \[study\] runner = 'this:s': unknown runner; import paths are no longer "
     r"accepted, name a registered runner; known runners: .*pipeline"),
    ("study runner os.system", lambda c, w: ["study", str(_study_file(w, "os:system"))],
     r"runner = 'os:system': unknown runner; import paths are no longer accepted"),
    ("study runner misspelt", lambda c, w: ["study", str(_study_file(w, "pipline"))],
     r"runner = 'pipline': unknown runner \(did you mean 'pipeline'\?\)"),
    ("study --runner import path",
     lambda c, w: ["study", str(_study_file(w, "pipeline")), "--runner", "os:getcwd"],
     r"--runner 'os:getcwd': unknown runner; import paths are no longer accepted"),
    ("study --out names a file",
     lambda c, w: ["study", str(_study_file(w, "pipeline")), "--out", str(_file(w))],
     r"^regtrack study: error: --out .*afile: is a file, not a folder"),
    ("calibrate --cache names a file",
     lambda c, w: ["calibrate", str(c), "--cache", str(_file(w)), "--out", str(w / "cal")],
     r"^regtrack calibrate: error: --cache .*afile: is a file, not a folder"),
    ("calibrate --runner import path",
     lambda c, w: ["calibrate", str(c), "--runner", "os:getcwd", "--out", str(w / "cal")],
     r"^regtrack calibrate: error: --runner 'os:getcwd': unknown runner; import paths are no "
     r"longer accepted"),
]


def _cut(src: Path, work: Path, fraction: float) -> Path:
    b = src.read_bytes()
    (work / "cut.nii.gz").write_bytes(b[: int(len(b) * fraction)])
    return work / "cut.nii.gz"


def _poly(work: Path, points: list) -> Path:
    (work / "poly.json").write_text(json.dumps({"points_rc": points}))
    return work / "poly.json"


@pytest.mark.parametrize("name, argv, message", ARGS, ids=[a[0] for a in ARGS])
def test_bad_option_gives_one_error_before_any_work(tmp_path: Path, name: str, argv, message: str,
                                                    capsys, monkeypatch) -> None:
    case_dir = build_case(tmp_path / "synth01")
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    args = argv(case_dir, work)
    before = snapshot(tmp_path)
    capsys.readouterr()
    rc = main(["-q", *args])
    err = capsys.readouterr().err
    assert rc == 2, (rc, err)
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("regtrack ")]
    assert len(lines) == 1 and lines[0].startswith(f"regtrack {args[0]}: error: "), err
    assert re.search(message, lines[0]), lines[0]
    assert snapshot(tmp_path) == before  # nothing written, not even an empty folder
    assert not any(p.is_dir() for p in work.iterdir())  # no output or cache folder made


def test_read_only_output_folder_is_refused_first(tmp_path: Path, capsys, monkeypatch) -> None:
    """A read-only --out (permissions, or a read-only file system: ``os.access`` reports
    both; tests run as root here, for whom permission bits do not bind, so the answer is
    simulated) is refused before the case is read; so is a read-only --cache."""
    import os

    case_dir = build_case(tmp_path / "synth01")
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access",
                        lambda p, mode, **kw: False if Path(p) == ro else real(p, mode, **kw))
    for opt in ("--out", "--cache"):
        rc = main(["-q", "run", str(case_dir), opt, str(ro / "sub")])
        err = capsys.readouterr().err
        assert rc == 2 and "Traceback" not in err
        assert err.strip() == (f"regtrack run: error: {opt} {ro / 'sub'}: the parent folder {ro} "
                               f"is not writable (read-only); give a writable {opt} folder")
    assert list(ro.iterdir()) == []
