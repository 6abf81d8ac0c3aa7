"""The DICOM's acquisition geometry (issue 52): read, checked, resolved against case.toml.

Known answers: a cone-beam projection of a point at a known height lands where the closed
form says; BodyPartThickness in gives that final plate gap out (the protocol engine with
the mock body of ``test_protocol_engine``); a daN compression force is recognised; the
MLO angle is the magnitude of PositionerPrimaryAngle.  A fuzz of the geometry tags
(missing, zero, negative, huge, wrong VR) gives warnings, never an exception.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from regtrack.errors import ConfigError
from regtrack.imaging.mammogram.geometry import RANGES, read_geometry, read_geometry_file
from regtrack.pipeline.geometry import GeometryInputs, resolve_geometry
from regtrack.virtual import xray
from regtrack.virtual.config import VirtualConfig
from regtrack.virtual.project import _point_source


def _ds(**tags) -> Dataset:
    ds = Dataset()
    ds.Modality, ds.Manufacturer = "MG", "ACME"
    ds.PixelSpacing = ds.ImagerPixelSpacing = [0.1, 0.1]
    for k, v in tags.items():
        if v is None:
            if k in ds:
                delattr(ds, k)
        else:
            setattr(ds, k, v)
    return ds


def _write(path: Path, ds: Dataset) -> Path:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1.2"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID
    ds.save_as(path, enforce_file_format=True)
    return path


def _ctx(tmp_path, views: dict[str, Dataset], tables=None, virtual=None):
    vi = {v: SimpleNamespace(mammogram=_write(tmp_path / f"{v.lower()}.dcm", ds))
          for v, ds in views.items()}
    case = SimpleNamespace(views=vi, toml_path=tmp_path / "case.toml", root=tmp_path)
    return GeometryInputs(case, {v: dict((tables or {}).get(v, {})) for v in views},
                          virtual or VirtualConfig())


# -- cone beam ---------------------------------------------------------------------------
@pytest.mark.parametrize("support_calibrated", [False, True])
def test_cone_beam_projection_of_a_point_at_a_known_height(tmp_path, support_calibrated):
    """SID 650 mm, source 630 mm above the support: a point 25 mm above the support, 60 mm
    from the central ray, lands at 60 * 650 / (630 - 25) = 64.46 mm on the detector (the
    issue's 'about 4 mm' of magnification); on an image calibrated at the support
    (ImagerPixelSpacing / EstimatedRadiographicMagnificationFactor), at 60 * 630 / 605."""
    tags: dict = {"DistanceSourceToDetector": 650, "DistanceSourceToPatient": 630}
    if support_calibrated:
        tags.update(PixelSpacing=None, EstimatedRadiographicMagnificationFactor=650 / 630)
    geo = resolve_geometry(_ctx(tmp_path, {"CC": _ds(**tags)}))["CC"]
    cfg = geo.virtual
    assert geo.projection.value.startswith("cone beam")
    assert "DistanceSourceToDetector" in geo.projection.source
    # the pipeline's own source placement: above the middle of the chest-wall edge
    local = np.array([[0.0, -20.0, 0.0], [0.0, 20.0, 0.0], [60.0, 0.0, 25.0], [60.0, 0.0, 0.0]])
    model = SimpleNamespace(fixed=np.array([True, True, False, False]))
    src = _point_source(cfg, local, model)
    assert src.foot == (0.0, 0.0)
    xy = xray.projected_xy(local, src)
    image = 650.0 if not support_calibrated else 630.0
    np.testing.assert_allclose(xy[2], [60.0 * image / (630.0 - 25.0), 0.0], atol=1e-9)
    np.testing.assert_allclose(xy[3], [60.0 * image / 630.0, 0.0], atol=1e-9)
    if not support_calibrated:
        assert xy[2, 0] - 60.0 == pytest.approx(4.46, abs=0.01)


def test_orthogonal_projection_stays_available(tmp_path):
    ds = _ds(DistanceSourceToDetector=650, DistanceSourceToPatient=630)
    geo = resolve_geometry(_ctx(tmp_path, {"CC": ds},
                                virtual=VirtualConfig(projection="orthogonal")))["CC"]
    assert geo.virtual.source_to_image_mm == 0.0 and geo.projection.value == "orthogonal"
    assert "config" in geo.projection.source
    # no distances in the header: orthogonal by default; 'cone' then says what to set
    geo = resolve_geometry(_ctx(tmp_path, {"CC": _ds()}))["CC"]
    assert geo.projection.value == "orthogonal" and geo.projection.source.startswith("default")
    with pytest.raises(ConfigError, match="source_to_image_mm"):
        resolve_geometry(_ctx(tmp_path, {"CC": _ds()}, virtual=VirtualConfig(projection="cone")))


# -- plate gap and angle -----------------------------------------------------------------
def _run_protocol(view: str, table: dict):
    from regtrack.mechanics.contact import ContactConfig
    from regtrack.mechanics.protocol import protocol_for_view
    from regtrack.mechanics.protocol_run import ProtocolRunner
    from tests.test_protocol_engine import _body, mock_solver

    body = _body()
    runner = ProtocolRunner(body, protocol_for_view(view, table),
                            mock_solver(body.points, body.fixed),
                            config=ContactConfig(friction=0.1))
    return runner.run(), runner


def test_body_part_thickness_gives_the_final_plate_gap(tmp_path):
    """BodyPartThickness 20 mm on the 30 mm thick mock block: the protocol's last plate
    move ends at a 20 mm gap (within 0.1 mm; the engine drives the plate to the gap)."""
    ctx = _ctx(tmp_path, {"CC": _ds(BodyPartThickness=20)})
    geo = resolve_geometry(ctx)["CC"]
    assert geo.gap_source == "dicom" and geo.gap.value == 20.0
    assert ctx.protocol_tables["CC"] == {"target_gap_mm": 20.0}
    res, _ = _run_protocol("CC", ctx.protocol_tables["CC"])
    assert res.complete
    assert res.steps[-1].gap_mm == pytest.approx(20.0, abs=0.1)
    assert res.steps[-1].D == pytest.approx(1.0 - 20.0 / res.steps[-1].T0_mm, abs=1e-6)


def test_positioner_angle_sets_the_mlo_plates(tmp_path):
    """PositionerPrimaryAngle -50 (the sign is the side's rotation direction): plates at
    50 deg, n = cos50 y + sin50 m with m = -z for a right breast."""
    ctx = _ctx(tmp_path, {"MLO": _ds(PositionerPrimaryAngle=-50)})
    geo = resolve_geometry(ctx)["MLO"]
    assert geo.angle.value == 50.0 and "magnitude of -50" in geo.angle.source
    _, runner = _run_protocol("MLO", ctx.protocol_tables["MLO"])
    t = np.deg2rad(50.0)
    np.testing.assert_allclose(runner.plates["lower"].plate.normal, [0, np.cos(t), -np.sin(t)],
                               atol=1e-12)


def test_case_toml_overrides_the_dicom(tmp_path):
    ds = _ds(BodyPartThickness=20, PositionerPrimaryAngle=50)
    ctx = _ctx(tmp_path, {"MLO": ds}, tables={"MLO": {"target_D": 0.3, "angle_deg": 45.0}})
    geo = resolve_geometry(ctx)["MLO"]
    assert geo.gap.source == "case.toml [protocol.MLO] target_D" and geo.gap_source == "case.toml"
    assert geo.angle.value == 45.0 and geo.angle.source.startswith("case.toml")
    assert ctx.protocol_tables["MLO"] == {"target_D": 0.3, "angle_deg": 45.0}


def test_only_the_views_that_run_are_resolved(tmp_path):
    ctx = _ctx(tmp_path, {"CC": _ds(BodyPartThickness=20), "MLO": _ds(BodyPartThickness=400)})
    geo = resolve_geometry(ctx, views=("CC",))
    assert list(geo) == ["CC"] and ctx.protocol_tables["MLO"] == {}  # no MLO warning either


def test_thickness_checked_against_the_model(tmp_path):
    """A plausible tag that would barely compress this breast (D < 0.05) falls back, named."""
    model = SimpleNamespace(points=np.array([[0, 0, 0], [0, 30.0, 0], [10, 10, 10]]),
                            frame=SimpleNamespace(side="R"))
    ctx = _ctx(tmp_path, {"CC": _ds(BodyPartThickness=29)})
    geo = resolve_geometry(ctx, model)["CC"]
    assert geo.gap_source == "default" and ctx.protocol_tables["CC"] == {}
    assert any("BodyPartThickness (0018,11A0) = 29 mm" in w for w in geo.warnings)


# -- compression force -------------------------------------------------------------------
@pytest.mark.parametrize("stored, newtons, unit", [(12.0, 120.0, "daN"), (9, 90.0, "daN"),
                                                   (150.0, 150.0, "N"), (45, 45.0, "N")])
def test_compression_force_unit(stored, newtons, unit):
    g = read_geometry(_ds(CompressionForce=stored), view="CC")
    assert g.force_N == pytest.approx(newtons) and g.force_unit.split()[0] == unit
    assert g.force_raw == pytest.approx(stored) and not g.warnings


def test_an_implausible_force_is_named_with_both_units():
    g = read_geometry(_ds(CompressionForce=1.5), view="CC")
    assert g.force_N is None
    assert [w.split(": ", 1)[1] for w in g.warnings] == [
        "CompressionForce (0018,11A2) = 1.5 N is implausible (expected 2-300 N, or 2-30 daN); "
        "ignored, the case.toml value or the default is used"]


def test_force_is_reported_not_used(tmp_path):
    ctx = _ctx(tmp_path, {"CC": _ds(CompressionForce=11)})
    geo = resolve_geometry(ctx)["CC"]
    assert geo.row()["dicom_force_N"] == pytest.approx(110.0)
    assert "reported only" in geo.force.source and ctx.protocol_tables["CC"] == {}


# -- fuzz ---------------------------------------------------------------------------------
BAD = [("zero", "DS", "0"), ("negative", "DS", "-45"), ("huge", "DS", "1e9"),
       ("not a number", "LO", "abc"), ("two values", "DS", ["60", "61"]),
       ("binary", "OB", b"\x01\x02\x03\x04"), ("nan", "DS", "NaN")]


@pytest.mark.parametrize("keyword", list(RANGES))
@pytest.mark.parametrize("what, vr, value", BAD, ids=[b[0] for b in BAD])
def test_fuzzed_geometry_tags_warn_and_fall_back(tmp_path, keyword, what, vr, value):
    from pydicom.datadict import tag_for_keyword

    ds = _ds()
    ds.add_new(tag_for_keyword(keyword), vr, value)
    path = tmp_path / "x.dcm"
    try:
        _write(path, ds)
    except Exception:  # noqa: BLE001 - pydicom refuses to write some of them: test in memory
        written = False
        g = read_geometry(ds, name="x.dcm", view="MLO")
    else:
        written = True
        g = read_geometry_file(path, name="x.dcm", view="MLO")
    attr = {"BodyPartThickness": "thickness_mm", "CompressionForce": "force_N",
            "PositionerPrimaryAngle": "angle_deg", "DistanceSourceToDetector": "sid_mm",
            "DistanceSourceToPatient": "ssd_mm",
            "EstimatedRadiographicMagnificationFactor": "magnification"}[keyword]
    if keyword == "PositionerPrimaryAngle" and what == "negative":
        assert g.angle_deg == 45.0 and not g.warnings  # -45: the other side's direction
        return
    assert getattr(g, attr) is None
    assert len(g.warnings) == 1 and keyword in g.warnings[0] and "\n" not in g.warnings[0]
    if not written:
        return
    # the run goes on: the resolver uses the defaults
    geo = resolve_geometry(_ctx(tmp_path, {"MLO": ds}))["MLO"]
    assert geo.gap_source == "default" and geo.projection.value == "orthogonal"


@pytest.mark.parametrize("keyword", list(RANGES))
def test_garbage_bytes_in_a_file_warn(tmp_path, keyword):
    """A DS value whose bytes are garbage in the file (as a broken exporter writes it)."""
    p = _write(tmp_path / "g.dcm", _ds(**{keyword: "987654"}))
    p.write_bytes(p.read_bytes().replace(b"987654", b"\x01\x02ab\xff\x00"))
    g = read_geometry_file(p, name="g.dcm", view="MLO")
    assert len(g.warnings) == 1 and keyword in g.warnings[0]


def test_missing_tags_are_silent():
    g = read_geometry(_ds(), view="MLO")
    assert g.warnings == [] and g.thickness_mm is None and g.sid_mm is None


def test_unreadable_file_is_a_warning(tmp_path):
    p = tmp_path / "junk.dcm"
    p.write_bytes(b"not a dicom")
    g = read_geometry_file(p, view="CC")
    assert g.thickness_mm is None  # pydicom's force=True may parse it as an empty dataset


# -- end to end on the phantom -----------------------------------------------------------
@pytest.mark.slow
def test_phantom_with_geometry_tags_end_to_end(tmp_path):
    """phantom01's CC with BodyPartThickness 60 mm, a force of 9 (daN), SID 650 / SSD 630 mm:
    the simulated plate gap is 60 mm (within 0.1 mm), D = 1 - 60 / T0 is reported, the
    virtual mammogram is a cone-beam projection, and every source is in the provenance."""
    import json
    import os
    import shutil

    from regtrack.pipeline.run import run_case
    from tests.conftest import REPO, SAMPLE_CASES

    case = tmp_path / "phantom01"
    shutil.copytree(SAMPLE_CASES / "phantom01", case, ignore=shutil.ignore_patterns("truth"))
    ds = pydicom.dcmread(case / "mammo" / "cc.dcm")
    ds.BodyPartThickness, ds.CompressionForce = 60, 9
    ds.DistanceSourceToDetector, ds.DistanceSourceToPatient = 650, 630
    ds.save_as(case / "mammo" / "cc.dcm")
    cache = os.environ.get("REGTRACK_CACHE", str(REPO / ".regtrack-cache"))
    (row,) = run_case(case, views=["CC"], cache_dir=cache, out_dir=tmp_path / "out")
    assert row["plate_gap_mm"] == pytest.approx(60.0, abs=0.1)
    assert row["gap_source"] == "dicom" and row["dicom_thickness_mm"] == 60.0
    assert row["dicom_force_N"] == pytest.approx(90.0) and row["force_N"] > 0
    assert row["projection"] == "cone"
    sim = json.loads((tmp_path / "out" / "cc" / "simulation.json").read_text())["summary"]
    assert row["D"] == pytest.approx(1.0 - 60.0 / sim["T0_mm"], abs=1e-6)
    geo = json.loads((tmp_path / "out" / "provenance.json").read_text())["geometry"]["CC"]
    assert geo["final_plate_gap"]["source"] == "DICOM BodyPartThickness (0018,11A0)"
    assert geo["compression_force"]["source"].startswith("DICOM CompressionForce (0018,11A2), unit daN")
    assert geo["projection"]["source"].startswith("DICOM DistanceSourceToDetector")
    assert geo["projection"]["value"].startswith("cone beam, SID 650 mm, source 630 mm")
    import csv

    head, cells = list(csv.reader((tmp_path / "out" / "metrics.csv").open()))
    assert len(head) == len(cells) and cells[head.index("projection")] == "cone"
    assert geo["plate_angle"]["source"] == "default (protocol)"
