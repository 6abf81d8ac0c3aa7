"""Privacy (issue 10, part 4): planted patient identifiers never reach an output.

Unit tests of :mod:`regtrack.privacy` (identifier forms, scrubbing, pseudonymous ids,
basic-profile de-identification of written DICOM), and one end-to-end run:

The case (built in ``tmp_path``) plants identifiers everywhere a user's data could carry
them: the DICOM mammogram's PatientName, PatientID, PatientBirthDate, AccessionNumber,
InstitutionName, ReferringPhysicianName and OperatorsName; the case folder's name
(``Zubrowka_Jadwiga``); a case id holding the patient ID and a title holding the name.  The run
(``run_case``, as ``regtrack run`` does) then writes JSON, CSV, PNGs and the PDF; the
test scans

* the bytes of every file under the output folder and the stage cache (PNG text chunks
  and PDF metadata included), the decompressed PDF streams,
* every string drawn in a matplotlib figure (``Text.draw`` is recorded, so text rendered
  into PNG pixels is covered too),
* every log record (DEBUG and up) and every progress line,

for every form of every planted value (``Zubrowka^Jadwiga``, ``Jadwiga Zubrowka``,
``Zubrowka``, ``1961-02-14``, ...).  With ``keep_identifiers=True`` the identifiers appear in ``provenance.json`` (so
the scan is not blind).

The patient model is a gmsh hemisphere (R = 50 mm, 10 mm tumour) put in place of the
label-map mesher (``regtrack.model.build.build_model``), whose owner is still changing it
and which needs minutes on a loaded 2-core machine; every other stage is the real one.
"""

from __future__ import annotations

import logging
import re
import zlib
from pathlib import Path

import numpy as np
import pytest

from regtrack.privacy import (
    Identifiers,
    collect_identifiers,
    deidentify_dataset,
    dicom_leaks,
    pseudonymous_id,
    read_identifiers,
    scrub_logs,
)

# distinctive values: a 3-letter name such as "Doe" occurs by chance in megabytes of
# binary mesh data (measured: it did in model.vtu), which would make the scan flaky
PLANTED = {
    "PatientName": "Zubrowka^Jadwiga",
    "PatientID": "PID7731902",
    "PatientBirthDate": "19610214",
    "AccessionNumber": "ACC55102",
    "InstitutionName": "St Elsewhere Hospital",
    "ReferringPhysicianName": "Housekeeper^Gregor",
    "OperatorsName": "Tech^Quincy",
}
CASE_ID = "case-PID7731902"  # a careless id holding the patient ID


# ----------------------------------------------------------------------------- builders
def write_e2e_case(root: Path, *, case_id: str = "rt01", identifiers: dict | None = None,
                   title: str = "e2e test case", target_nodes: int | None = None) -> Path:
    """A small runnable case: the tiny label map of ``tests/test_case.py`` and a 600 x 400
    synthetic right CC mammogram (0.25 mm pixels, IHE stored orientation) with a 6 mm
    tumour and its polygon; ``identifiers`` are written into the DICOM header."""
    import json

    from regtrack.imaging.mammogram.synthetic import synthetic_breast, write_dicom
    from tests.test_case import label_data, write_labels

    write_labels(root / "mri" / "labels.nii.gz", label_data())
    sb = synthetic_breast(shape=(600, 400), spacing=(0.25, 0.25), a_mm=60, b_mm=50, yc_mm=75,
                          tumour_mm=(30, 70, 6), label=False, film_edge_mm=0)
    (root / "mammo").mkdir(parents=True, exist_ok=True)
    write_dicom(root / "mammo" / "cc.dcm", np.round(sb.image * 4000)[:, ::-1],
                ImageLaterality="R", ViewPosition="CC", PixelSpacing=[0.25, 0.25],
                PatientOrientation=["P", "L"], **(identifiers or {}))
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    col, row = 399 - 30 / 0.25, 70 / 0.25
    poly = np.c_[row + 24 * np.sin(t), col + 24 * np.cos(t)]
    (root / "mammo" / "cc_tumour.json").write_text(json.dumps({"points_rc": poly.tolist()}))
    extra = f"\n[model]\ntarget_nodes = {target_nodes}\n" if target_nodes else ""
    (root / "case.toml").write_text(f'''[case]
id = "{case_id}"
title = "{title}"
[mri]
labels = "mri/labels.nii.gz"
scheme = "pelicano-detailed"
side = "R"
[views.CC]
mammogram = "mammo/cc.dcm"
tumour_polygon = "mammo/cc_tumour.json"
{extra}''')
    return root


def hemisphere_build_model(labels, **kwargs):
    """Stand-in for ``regtrack.model.build.build_model``: a 50 mm hemisphere, 10 mm tumour."""
    from regtrack.mechanics.meshes import hemisphere_model

    return hemisphere_model(50.0, 14.0, tumour_radius=10.0)


# ----------------------------------------------------------------------------- units
def test_identifier_forms_and_scrubbing() -> None:
    ids = Identifiers()
    for k, v in {**PLANTED, "PatientName": "Doe^Jane"}.items():
        ids.add(k, v)
    for form in ("Doe^Jane", "Jane Doe", "Doe, Jane", "Doe_Jane", "Jane", "1961-02-14",
                 "PID7731902", "St Elsewhere Hospital", "Gregor"):
        assert form in ids.values, form
    text = "case of JANE DOE (pid7731902), born 1961-02-14 at St Elsewhere Hospital"  # any case
    clean = ids.scrub(text)
    assert ids.found_in(clean) == [] and clean.count("[redacted]") == 4
    obj = ids.scrub_obj({"a": ["Doe^Jane", {"Doe": 1.5}], "b": Path("/x/Doe_Jane/c.dcm")})
    assert obj == {"a": ["[redacted]", {"[redacted]": 1.5}], "b": "/x/[redacted]/c.dcm"}
    # placeholders and 1-2 character values are not identifiers (they would scrub "F", "1")
    ids2 = Identifiers()
    ids2.add("PatientID", "ANONYMOUS")
    ids2.add("StudyID", "1")
    ids2.add("PatientName", "Li^Wu")
    assert ids2.values == {"Li^Wu", "Wu Li", "Li Wu", "Li, Wu", "Li_Wu", "Wu_Li"}


def test_pseudonymous_id_replaces_an_identifying_case_id(caplog) -> None:
    ids = Identifiers()
    ids.add("PatientID", "PID7731902")
    assert pseudonymous_id("breast01", ids) == "breast01"
    with caplog.at_level(logging.WARNING, logger="regtrack.privacy"):
        p = pseudonymous_id(CASE_ID, ids)
    assert re.fullmatch(r"anon-[0-9a-f]{8}", p) and p == pseudonymous_id(CASE_ID, ids)
    assert "PID7731902" not in caplog.text and p in caplog.text


def test_scrub_logs_filters_every_handler(caplog) -> None:
    ids = Identifiers()
    ids.add("PatientName", "Doe^Jane")
    log = logging.getLogger("regtrack.test_privacy")
    # the logger's own level too: `regtrack run` (in-process in other tests) quiets "regtrack"
    with caplog.at_level(logging.DEBUG, logger="regtrack.test_privacy"), scrub_logs(ids):
        log.info("reading %s for %s", "/data/Doe_Jane/cc.dcm", "Jane Doe")
    log.info("after: %s", "Doe")  # the filter is removed afterwards
    assert "reading /data/[redacted]/cc.dcm for [redacted]" in caplog.text
    assert "Doe_Jane" not in caplog.records[0].getMessage()


def test_deidentified_dicom_follows_the_basic_profile(tmp_path: Path) -> None:
    from regtrack.imaging.mammogram.synthetic import write_dicom

    p = write_dicom(tmp_path / "in.dcm", np.zeros((8, 8)), PatientBirthDate="19610214",
                    StudyDate="20240101", **{k: v for k, v in PLANTED.items()
                                             if k != "PatientBirthDate"})
    import pydicom

    ds = pydicom.dcmread(p)
    ds.add_new(0x00091001, "LO", "private vendor tag")
    assert len(dicom_leaks(p)) >= 5
    deidentify_dataset(ds, pseudonym="rt01")
    ds.save_as(tmp_path / "out.dcm")
    assert dicom_leaks(tmp_path / "out.dcm", pseudonym="rt01") == []
    out = pydicom.dcmread(tmp_path / "out.dcm")
    assert out.PatientName == "rt01" and out.PatientID == "rt01"
    assert out.PatientBirthDate == "" and out.StudyDate == "" and "InstitutionName" not in out
    assert out.PatientIdentityRemoved == "YES"
    assert out.DeidentificationMethodCodeSequence[0].CodeValue == "113100"
    left = read_identifiers(tmp_path / "out.dcm").by_keyword
    assert left == {"PatientName": ["rt01"], "PatientID": ["rt01"]}  # the pseudonym only
    raw = (tmp_path / "out.dcm").read_bytes()
    assert b"Zubrowka" not in raw and b"7731902" not in raw and b"Elsewhere" not in raw


def test_written_mr_series_is_deidentified(tmp_path: Path) -> None:
    """DICOM the tool writes (``write_dicom_series``: the phantom MR series) passes the
    basic-profile scan with its pseudonym."""
    from regtrack.imaging.dicom_series import write_dicom_series
    from regtrack.imaging.volume import ImageVolume

    vol = ImageVolume(np.arange(4 * 5 * 3, dtype=np.int16).reshape(4, 5, 3), np.eye(4))
    files = write_dicom_series(vol, tmp_path / "s", patient="phantom01",
                               transfer_syntax="explicit")
    for f in files:
        assert dicom_leaks(f, pseudonym="phantom01") == [], f


# ----------------------------------------------------------------------------- end to end
def _pdf_text(data: bytes) -> str:
    """Raw PDF plus every FlateDecode stream decompressed (latin-1 text)."""
    out = [data.decode("latin-1")]
    for m in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            out.append(zlib.decompress(m.group(1)).decode("latin-1"))
        except zlib.error:
            pass
    return "\n".join(out)


def _vtk_text(data: bytes) -> str:
    """A VTK XML file without the payloads of its binary data arrays: those are base64 of
    zlib-compressed numbers, which hold no text but match a short name component (``Tech``)
    by chance at about 1e-6 per character; the tags, attributes and array names stay."""
    return re.sub(r'(<DataArray\b[^>]*format="binary"[^>]*>).*?(</DataArray>)', r"\1\2",
                  data.decode("latin-1"), flags=re.S)


def _file_texts(folder: Path) -> dict[str, str]:
    texts = {}
    for p in sorted(q for q in folder.rglob("*") if q.is_file()):
        data = p.read_bytes()
        text = (_pdf_text(data) if p.suffix == ".pdf" else
                _vtk_text(data) if p.suffix in (".vtu", ".vtp") else data.decode("latin-1"))
        texts[str(p.relative_to(folder))] = text
    return texts


def _forms() -> Identifiers:
    ids = Identifiers()
    for k, v in PLANTED.items():
        ids.add(k, v)
    ids.add("PatientName", "Zubrowka_Jadwiga")  # the case folder's name
    return ids


@pytest.fixture(scope="module")
def e2e(tmp_path_factory):
    """Run the planted case once (identifiers removed) and record everything it emits."""
    import matplotlib.text

    import regtrack.model.build as build
    from regtrack.pipeline.run import run_case

    tmp = tmp_path_factory.mktemp("privacy")
    case = write_e2e_case(tmp / "Zubrowka_Jadwiga" / "exam", case_id=CASE_ID,
                          identifiers=PLANTED, title="Mammography of Jadwiga Zubrowka")
    drawn: list[str] = []
    original_draw = matplotlib.text.Text.draw

    def recording_draw(self, renderer):
        drawn.append(self.get_text())
        return original_draw(self, renderer)

    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(self.format(record))

    handler = Keep(level=logging.DEBUG)
    root = logging.getLogger()  # the handler sits where the CLI's handler sits
    lib = logging.getLogger("regtrack")
    saved = lib.level
    root.addHandler(handler)
    lib.setLevel(logging.DEBUG)
    progress: list[str] = []
    mp = pytest.MonkeyPatch()
    mp.setattr(build, "build_model", hemisphere_build_model)
    mp.setattr(matplotlib.text.Text, "draw", recording_draw)
    try:
        rows = run_case(case, cache_dir=tmp / "cache", out_dir=tmp / "out",
                        progress=progress.append)
    finally:
        mp.undo()
        root.removeHandler(handler)
        lib.setLevel(saved)
    return {"tmp": tmp, "case": case, "rows": rows, "drawn": drawn, "logs": records,
            "progress": progress}


@pytest.mark.slow
def test_planted_identifiers_never_reach_an_output(e2e) -> None:
    ids = _forms()
    out, cache = e2e["tmp"] / "out", e2e["tmp"] / "cache"
    files = _file_texts(out)
    assert {"metrics.json", "metrics.csv", "provenance.json", "report.pdf", "cc/real.json",
            "cc/overlay.png", "cc/images.png"} <= set(files)
    leaks = {name: ids.found_in(text) for name, text in {**files, **{
        f"cache/{k}": v for k, v in _file_texts(cache).items()}}.items()}
    assert {k: v for k, v in leaks.items() if v} == {}
    assert ids.found_in("\n".join(e2e["drawn"])) == []  # text rendered into PNG/PDF pixels
    assert len(e2e["drawn"]) > 20  # the recorder saw the figures' text
    assert ids.found_in("\n".join(e2e["logs"])) == [] and len(e2e["logs"]) > 5
    assert ids.found_in("\n".join(e2e["progress"])) == []
    # the case id held the patient ID: every output is named by the pseudonym instead
    import json

    pseudo = json.loads((out / "metrics.json").read_text())["case_id"]
    assert re.fullmatch(r"anon-[0-9a-f]{8}", pseudo)
    assert all(r["case_id"] == pseudo for r in e2e["rows"])
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["privacy"]["identifiers"] == "removed"
    # and the inputs were not touched: the planted values are still in the input DICOM
    assert read_identifiers(e2e["case"] / "mammo" / "cc.dcm").by_keyword["PatientID"] == ["PID7731902"]


@pytest.mark.slow
def test_keep_identifiers_copies_them_into_provenance(e2e) -> None:
    """The opt-in: same case and cache (mesh and simulation re-used), identifiers kept."""
    import json

    import regtrack.model.build as build
    from regtrack.pipeline.run import run_case

    mp = pytest.MonkeyPatch()
    mp.setattr(build, "build_model", hemisphere_build_model)
    try:
        run_case(e2e["case"], cache_dir=e2e["tmp"] / "cache", out_dir=e2e["tmp"] / "kept",
                 report=False, keep_identifiers=True)
    finally:
        mp.undo()
    prov = json.loads((e2e["tmp"] / "kept" / "provenance.json").read_text())
    assert prov["privacy"]["patient"]["PatientID"] == ["PID7731902"]
    assert prov["privacy"]["patient"]["InstitutionName"] == ["St Elsewhere Hospital"]
    metrics = json.loads((e2e["tmp"] / "kept" / "metrics.json").read_text())
    assert metrics["case_id"] == CASE_ID
    # the scan finds them, so a clean scan above means clean outputs
    assert "PID7731902" in _forms().found_in((e2e["tmp"] / "kept" / "provenance.json").read_text())


def test_collect_identifiers_reads_the_case_headers(tmp_path: Path) -> None:
    from regtrack.case import load_case

    case = load_case(write_e2e_case(tmp_path / "c", identifiers=PLANTED), deep=False)
    ids = collect_identifiers(case)
    assert ids.by_keyword["PatientName"] == ["Zubrowka^Jadwiga"]
    assert ids.by_keyword["AccessionNumber"] == ["ACC55102"]
    assert ids.paths[str((tmp_path / "c").resolve())] == "<case>"


def test_study_and_calibration_name_an_identifying_case_by_its_pseudonym(tmp_path: Path) -> None:
    """Studies and calibration name cases by ``case_id_of`` (table rows, figure file names,
    calibration.json): a case id holding the DICOM PatientID becomes the same pseudonym as
    in ``regtrack run``; a harmless id is kept."""
    from regtrack.privacy import identifiers_of_case_folder, pseudonymous_id
    from regtrack.study.spec import case_id_of

    bad = write_e2e_case(tmp_path / "a", case_id=CASE_ID, identifiers=PLANTED)
    cid = case_id_of(bad)
    assert cid.startswith("anon-") and "PID7731902" not in cid
    assert cid == pseudonymous_id(CASE_ID, identifiers_of_case_folder(bad))
    ok = write_e2e_case(tmp_path / "b", case_id="rt01", identifiers=PLANTED)
    assert case_id_of(ok) == "rt01"


def test_a_redacted_title_is_announced(caplog) -> None:
    """Issue 53: a title holding a name and a birth date was redacted silently.  The
    warning names the field and the kinds of identifier, never their values."""
    ids = Identifiers()
    ids.add("PatientName", "Roe^Richard")
    ids.add("PatientBirthDate", "19550101")
    with caplog.at_level(logging.WARNING, logger="regtrack"):
        title = ids.redact("Richard Roe, born 1955-01-01: screening", "[case] title")
    assert title == "[redacted], born [redacted]: screening"
    assert ("[case] title contains DICOM patient identifiers (PatientName, PatientBirthDate)"
            in caplog.text)
    assert "Roe" not in caplog.text and "1955" not in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="regtrack"):
        assert ids.redact("synthetic", "[case] title") == "synthetic"
    assert caplog.text == ""


def test_mesh_json_holds_no_folder_names() -> None:
    """``regtrack mesh`` wrote the label map's absolute path into the model's JSON; its
    folders often carry the patient's name (issue 53).  Only the file name is kept."""
    import argparse
    from types import SimpleNamespace

    from regtrack.cli.mesh import _drop_paths

    model = SimpleNamespace(meta={"source": "/data/Doe_Jane_19610304/mri/labels.nii.gz",
                                  "quality": {"gamma_p5": 0.4}})
    _drop_paths(model, argparse.Namespace(case=None))
    assert model.meta == {"source": "labels.nii.gz", "quality": {"gamma_p5": 0.4}}
