"""Tracking mode and paper mode of ``regtrack run`` on ``sample_cases/phantom01`` (issue 52).

A copy of the phantom without its tumour outlines runs end to end in tracking mode: the
registration uses the breast outline and nipple only and the MRI tumour is predicted on
each mammogram; the prediction is compared with the phantom's hidden truth
(``truth/mammo_truth.json``: the projected mass centroid of the true tumour, canonical mm).
The original case runs in paper mode and also reports the prediction's error against its
outline.  With ``[registration] use_tumour = false`` and outlines given, d_T is the error
of the breast-only registration (the crash of issue 52, "TS_Av = nan is not finite", is
gone).

Figures pinned (coarse 1,841-node phantom model, shipped protocols, orthogonal projection:
the phantom's DICOMs carry no geometry tags): tracking-mode centroid errors 2.9 mm (CC)
and 0.7 mm (MLO) at 1-sigma radii of 1.4 and 2.6 mm.  Asserted: within issue 9's 3 mm,
and within 3 sigma.  In paper mode the same prediction is measured against the given
outline's area centroid, which lies apart from the true mass centroid: 3.09 mm on the CC,
asserted within the 3 mm plus that offset.  The mesh and simulations come from the stage cache
(``$REGTRACK_CACHE`` or the repository's ``.regtrack-cache``): every run here after the
first re-uses them, since annotations do not enter the simulations' keys.
"""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from tests.conftest import REPO, SAMPLE_CASES

pytestmark = pytest.mark.slow

CASE = SAMPLE_CASES / "phantom01"
TRUTH = CASE / "truth" / "mammo_truth.json"
CACHE = os.environ.get("REGTRACK_CACHE", str(REPO / ".regtrack-cache"))
TOL_MM = 3.0  # issue 9's acceptance for the MRI tumour centroid in each view


def _truth_mm(view: str) -> np.ndarray:
    doc = json.loads(TRUTH.read_text())
    return np.asarray(doc["views"][view]["tumour"]["volume_centroid_projected_canonical_mm"], float)


def without_outlines(dst):
    """A copy of phantom01 whose mammograms carry no tumour annotation."""
    case = dst / "phantom01"
    shutil.copytree(CASE, case, ignore=shutil.ignore_patterns("*_tumour.json", "truth"))
    toml = case / "case.toml"
    toml.write_text("\n".join(line for line in toml.read_text().splitlines()
                              if not line.startswith("tumour_polygon")) + "\n")
    return case


@pytest.fixture(scope="module")
def tracking(tmp_path_factory):
    from regtrack.pipeline.run import run_case

    if not TRUTH.is_file():
        pytest.skip(f"{TRUTH} not generated (pipelines/make_sample_cases.py)")
    tmp = tmp_path_factory.mktemp("tracking")
    out = tmp / "out"
    rows = run_case(without_outlines(tmp), cache_dir=CACHE, out_dir=out)
    return rows, out


def test_a_case_without_outlines_runs_in_tracking_mode(tracking):
    rows, out = tracking
    assert [r["view"] for r in rows] == ["CC", "MLO"]
    for r in rows:
        assert r["mode"] == "tracking"
        assert r["TS_Av"] is None and r["theta_p_t"] is None and r["d_T"] is None
        assert r["theta_p"] == r["theta_p_b"]
        assert r["n_lesions"] == 1 and r["lesion_error_mm"] is None
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["mode"] == "tracking"
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["mode"] == "tracking"
    assert prov["view_modes"]["CC"]["why"] == "no tumour outline on the mammogram"
    assert (out / "report.pdf").read_bytes()[:5] == b"%PDF-"


def test_dicom_sr_of_the_predictions(tracking):
    """The SR written by the run holds each view's predicted centroid in DICOM pixels."""
    hd = pytest.importorskip("highdicom")
    rows, out = tracking
    sr = hd.sr.srread(out / "dicom" / "sr_1.dcm")
    groups = {str(g.tracking_identifier): g for g in sr.content.get_planar_roi_measurement_groups()}
    for r in rows:
        c = groups[f"MRI lesion 1 on {r['view']}: centroid"].roi.value
        np.testing.assert_allclose(np.asarray(c, float).reshape(-1),
                                   [r["lesion_col_px"], r["lesion_row_px"]], atol=1e-3)
    # the phantom's MRI is a DICOM series: the lesion is also a 3-D point on it, at the
    # label map's tumour centroid (1.5 mm: the meshed tumour against its voxels at the
    # demo's 1,500 nodes)
    truth = json.loads((CASE / "truth" / "phantom_truth.json").read_text())
    point = groups["MRI lesion 1 on the MRI"].roi
    assert point.frame_of_reference_uid
    np.testing.assert_allclose(np.asarray(point.value, float).reshape(-1),
                               truth["tumour_centroid_lps_mm"], atol=1.5)
    assert (out / "dicom" / "report_1.dcm").is_file()


@pytest.mark.parametrize("view", ["CC", "MLO"])
def test_predicted_lesion_against_the_truth(tracking, view):
    rows, out = tracking
    les = json.loads((out / "lesions.json").read_text())["views"][view]["lesions"][0]
    xy = np.asarray(les["centroid_mm"])
    err = float(np.linalg.norm(xy - _truth_mm(view)))
    print(f"issue 52 figure: tracking mode {view}: {err:.2f} mm, sigma {les['sigma_mm']:.2f} mm")
    assert err < TOL_MM
    assert err < 3.0 * les["sigma_mm"]
    # sigma is the quadrature sum of its stated terms (the residual with its floor)
    t = les["uncertainty_terms_mm"]
    assert les["sigma_mm"] == pytest.approx(np.sqrt(max(t["registration_residual"], 0.5) ** 2
                                                    + t["rotation"] ** 2 + t["model"] ** 2
                                                    + t["nipple"] ** 2))
    # the outline is a polygon around the centroid, in mm and in DICOM pixels
    outline = np.asarray(les["outline_mm"])
    from shapely.geometry import Point, Polygon

    assert len(outline) >= 8 and Polygon(outline).contains(Point(*xy))
    assert len(les["outline_px_rc"]) == len(outline)
    row = next(r for r in rows if r["view"] == view)
    assert row["lesion_row_px"] == pytest.approx(les["centroid_px_rc"][0])
    # the registration's centre, the nipple found on the mammogram, in mm and in pixels:
    # the lesion's stated distance is measured from it, and it lies on the phantom's
    # projected nipple within the 3 mm of issue 9
    nip = np.asarray(les["nipple_mm"])
    assert les["distance_from_nipple_mm"] == pytest.approx(float(np.linalg.norm(xy - nip)))
    truth_nip = json.loads(TRUTH.read_text())["views"][view]["nipple"]
    assert np.linalg.norm(nip - truth_nip["canonical_mm"]) < TOL_MM
    px = float(json.loads(TRUTH.read_text())["views"][view]["pixel_mm"])
    assert np.linalg.norm(np.asarray(les["nipple_px_rc"]) - truth_nip["dicom_rc"]) * px < TOL_MM


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    from regtrack.pipeline.run import run_case

    out = tmp_path_factory.mktemp("paper") / "out"
    return run_case(CASE, cache_dir=CACHE, out_dir=out), out


def test_outlines_given_run_in_paper_mode_with_the_prediction_error(paper, tracking):
    rows, out = paper
    trk = {r["view"]: r for r in tracking[0]}
    doc = json.loads((out / "lesions.json").read_text())
    assert doc["mode"] == "paper"
    for r in rows:
        assert r["mode"] == "paper"
        assert np.isfinite(r["TS_Av"]) and np.isfinite(r["theta_p_t"]) and r["d_T"] < TOL_MM
        # the prediction comes from the breast-only registration: the same as tracking mode
        assert r["lesion_x_mm"] == pytest.approx(trk[r["view"]]["lesion_x_mm"], abs=1e-9)
        les = doc["views"][r["view"]]["lesions"][0]
        d = np.linalg.norm(np.subtract(les["centroid_mm"], les["annotated_centroid_mm"]))
        offset = float(np.linalg.norm(np.subtract(les["annotated_centroid_mm"],
                                                  _truth_mm(r["view"]))))
        assert r["lesion_error_mm"] == pytest.approx(d)
        assert r["lesion_error_mm"] < TOL_MM + offset
        print(f"issue 52 figure: paper mode {r['view']}: d_T {r['d_T']:.2f} mm, prediction "
              f"error {r['lesion_error_mm']:.2f} mm")


def test_use_tumour_false_with_outlines(tmp_path, paper):
    """Regression (issue 52): this gave 'TS_Av = nan is not finite' (exit 3)."""
    from regtrack.pipeline.run import run_case

    rows = run_case(CASE, cache_dir=CACHE, out_dir=None,
                    overrides={"registration": {"use_tumour": False}})
    by_view = {r["view"]: r for r in paper[0]}
    for r in rows:
        assert r["mode"] == "tracking" and r["TS_Av"] is None
        # d_T of the breast-only registration: the prediction's outline against the outline
        assert r["d_T"] is not None and r["d_T"] < TOL_MM
        assert r["lesion_error_mm"] == pytest.approx(by_view[r["view"]]["lesion_error_mm"])


def test_cli_run_and_validate_agree(tmp_path, tracking):
    import subprocess
    import sys

    case = without_outlines(tmp_path)
    v = subprocess.run([sys.executable, "-m", "regtrack.cli", "validate", str(case)],
                       check=False, capture_output=True, text=True, cwd=REPO)
    assert v.returncode == 0, v.stderr
    assert "tracking mode" in v.stdout + v.stderr
    r = subprocess.run([sys.executable, "-m", "regtrack.cli", "run", str(case), "--out",
                        str(tmp_path / "out"), "--cache", CACHE, "--serial-views"],
                       check=False, capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["mode"] == "tracking"


def test_each_predicted_lesion_is_scored_against_its_own_outline():
    """Paper mode with two lesions in the model and one outline on the image: the lesion
    near the outline is scored against it, the other gets no error (not the distance to
    an outline it does not belong to, nor to the centroid of a union)."""
    from regtrack.tracking.lesions import LesionPrediction, _score_against_outlines

    def lesion(k, xy):
        return LesionPrediction("CC", k, np.asarray(xy, float), None, None, 1.0, {}, 0.0, 0.1,
                                50.0, 0.0)

    square = np.array([[40.0, 20.0], [50.0, 20.0], [50.0, 30.0], [40.0, 30.0]])  # centroid (45, 25)
    far, near = lesion(1, [10.0, -60.0]), lesion(2, [47.0, 25.0])
    _score_against_outlines([far, near], [square])
    assert far.error_mm is None and far.annotated_mm is None
    assert near.error_mm == pytest.approx(2.0)
    np.testing.assert_allclose(near.annotated_mm, [45.0, 25.0])
    # two outlines, two lesions, listed in the other order: each with its own
    other = square + [-40.0, -80.0]  # centroid (5, -55)
    _score_against_outlines([far, near], [square, other])
    assert far.error_mm == pytest.approx(np.hypot(5.0, 5.0)) and near.error_mm == pytest.approx(2.0)


def test_a_lesion_off_the_detector_is_noted():
    """The share of a predicted outline on the image, by its clipped area: a 10 x 10 mm
    square wholly on a 100 x 140 mm image, a quarter of it across the chest-wall edge
    (x < 0), three quarters of it with its centroid off the image, and wholly beyond the
    bottom edge; an outline without area counts as its centroid."""
    from regtrack.tracking.lesions import (
        CENTROID_OFF,
        OUTSIDE_IMAGE,
        image_notes,
        on_image_fraction,
    )

    extent = (100.0, 140.0)
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])

    def check(shift, fraction):
        poly = square + shift
        f = on_image_fraction(poly, poly.mean(0), extent)
        assert f == pytest.approx(fraction, abs=1e-12)
        return image_notes(f, poly.mean(0), extent)

    assert check([40.0, 60.0], 1.0) == []
    notes = check([-2.5, 60.0], 0.75)
    assert notes == ["partly beyond the image edge: 75 % of its projected area on this mammogram"]
    notes = check([-7.5, 60.0], 0.25)
    assert len(notes) == 1 and notes[0].startswith("partly beyond the image edge: 25 %")
    assert notes[0].endswith(CENTROID_OFF)
    assert check([40.0, 141.0], 0.0) == [OUTSIDE_IMAGE]
    notes = check([-9.95, 60.0], 0.005)  # a sliver on the image
    assert notes[0].startswith("partly beyond the image edge: under 1 % of")
    notes = check([-0.05, 60.0], 0.995)  # a sliver off the image
    assert notes[0].startswith("partly beyond the image edge: over 99 % of")
    segment = np.array([[5.0, 5.0], [6.0, 6.0], [5.0, 5.0]])  # no area: the centroid decides
    assert on_image_fraction(segment, [5.5, 5.5], extent) == 1.0
    assert on_image_fraction(None, [-1.0, 5.0], extent) == 0.0
    assert image_notes(None, [-1.0, 5.0], extent) == []  # no extent known: nothing to say
