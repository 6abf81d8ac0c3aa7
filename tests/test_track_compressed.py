"""``regtrack track CASE --view cc|mlo|biopsy``: MRI landmarks in a simulated compression,
points of the compressed breast back to the MRI, and the warped MRI (issue 55, items 2-3).

The known answers of the maps and of the warp are in ``test_tracking_warp.py``; here the
command's bad inputs (each refused in one line before any mesh or simulation runs) and,
slow, the whole chain on the phantom's biopsy compression: the inverse map composed with
the forward one returns MRI points within the acceptance bound of 0.1 mm on a real
(nonlinear, frictional) FE deformation, and the warped label map keeps each tissue's
volume, since the tissue is nearly incompressible (nu = 0.49).
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import PIPELINE_CACHE

PHANTOM = Path(__file__).resolve().parents[1] / "sample_cases" / "phantom01"
#: The stage cache shared with the other phantom tests (test_registration_phantom,
#: test_mammogram_geometry, test_tracking_compare): the phantom's mesh is the pipeline's at
#: the case's settings, built once for all of them; the biopsy simulation at the defaults
#: serves test_tracking_compare too.
CACHE = PIPELINE_CACHE


@pytest.mark.parametrize("extra, message", [
    (["--landmarks", "x.csv"],
     r"--landmarks, --compressed-point, --warp, --uncertainty and --compare-\* need --view"),
    (["--warp"], r"need --view cc\|mlo\|biopsy"),
    (["--view", "biopsy"], r"--view biopsy: nothing to track; give --mri-point"),
    (["--view", "biopsy", "--cc-point", "1", "2"],
     r"--view biopsy tracks in 3-D: --cc-point belongs to the mammogram tracking"),
    (["--view", "biopsy", "--label", "tumour"], r"--label belongs to the mammogram tracking"),
    (["--view", "biopsy", "--compressed-point", "1", "nan", "3"],
     r"--compressed-point 1\.0 nan 3\.0: coordinates must be finite"),
    (["--view", "biopsy", "--landmarks", "missing.csv"], r"--landmarks .*missing\.csv"),
    (["--view", "biopsy", "--landmarks", "BAD"], r"row 1: 'q' is not a number"),
    (["--view", "biopsy", "--compare-landmarks", "x.csv"],
     r"--compare-landmarks needs --landmarks"),
    (["--view", "biopsy", "--compare-mri", "missing.nii.gz"], r"--compare-mri .*missing\.nii\.gz"),
    (["--view", "biopsy", "--mri-point", "1", "2", "3", "--no-simulate"],
     r"not in the cache .*; drop --no-simulate to compute them now"),
    (["--view", "biopsy", "--mri-point", "1", "2", "3", "--surrogate", "x"],
     r"--surrogate gives the --uncertainty terms; add --uncertainty"),
])
def test_bad_track_3d_arguments(tmp_path, capsys, extra, message):
    import re

    from regtrack.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("q,1,2\n")
    cache = tmp_path / "cache"
    argv = ["track", str(PHANTOM), "--cache", str(cache), "--out", str(tmp_path / "out"),
            *[str(bad) if a == "BAD" else a for a in extra]]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and re.search(message, " ".join(err.split())), err
    assert not cache.exists() or not any(cache.rglob("_complete.json"))  # nothing was run


@pytest.mark.slow
def test_track_and_warp_in_the_biopsy_compression(tmp_path, capsys):
    from regtrack.cli import main
    from regtrack.imaging.readers import read_label_map
    from regtrack.tracking.compressed import open_compressed
    from regtrack.tracking.deformation import DeformationMap
    from regtrack.tracking.warp import warp_volume

    cache, out = CACHE, tmp_path / "out"
    lm = tmp_path / "points.csv"
    lm.write_text("name,x,y,z\ntumour,-109.7,0.3,10.3\nfat,-100,-20,0\n")
    rc = main(["track", str(PHANTOM), "--view", "biopsy", "--landmarks", str(lm),
               "--compressed-point", "-105", "0", "5", "--warp", "--uncertainty",
               "--cache", str(cache), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    rows = list(csv.DictReader((out / "points_biopsy.csv").open()))
    assert [r["name"] for r in rows] == ["tumour", "fat", "compressed-point"]
    doc = json.loads((out / "points_biopsy.json").read_text())
    assert doc["compression"]["D"] == pytest.approx(0.26, abs=1e-9)
    # uncertainty: the plate moved by degree_sigma T0 more moves every point; scaling the
    # phantom's fat and gland c1 alike leaves the shape under a prescribed plate travel
    # without gravity unchanged (only the skin membrane keeps its own stiffness)
    for r in doc["points"]:
        t = r["sigma_terms_mm"]
        assert set(t) == {"c1", "nu", "plate"}
        assert t["plate"] > 0.5 and t["c1"] < 0.2 * t["plate"]
        assert r["sigma_mm"] == pytest.approx(np.sqrt(sum(v ** 2 for v in t.values())))
    # the state is cached now: reopened without simulating
    state = open_compressed(PHANTOM, "biopsy", cache_dir=cache, simulate=False)
    dmap = state.dmap
    mri = np.array([[float(r[f"mri_{a}"]) for a in "xyz"] for r in rows])
    comp = np.array([[float(r[f"compressed_{a}"]) for a in "xyz"] for r in rows])
    np.testing.assert_allclose(dmap.forward(mri), comp, atol=1e-3)  # the CSV's 3 decimals
    _check_biopsy_report(out / "biopsy.pdf", state, doc, rows)
    # inverse after forward on every element centroid of the model (acceptance: 0.1 mm)
    X = dmap.frame.to_patient(dmap.reference[dmap.tets].mean(axis=1))
    err = np.linalg.norm(dmap.inverse(dmap.forward(X)) - X, axis=1)
    assert err.max() < 0.1
    # the warped label map keeps each tissue's volume: compare with the identity warp
    # (the same resampling through the undeformed mesh); nu = 0.49 lets the volume change
    # by about 1 % (J = det F), the voxelisation of the surface adds about as much
    labels = read_label_map(PHANTOM / "mri" / "labels.nii.gz")
    warped = read_label_map(out / "labels_biopsy.nii.gz")
    same = warp_volume(labels, DeformationMap(dmap.reference, dmap.reference, dmap.tets,
                                              dmap.frame)).volume
    vox = float(np.prod(labels.spacing))
    for lab in np.unique(same.data[same.data > 0]):
        v0 = np.count_nonzero(same.data == lab) * vox
        v1 = np.count_nonzero(warped.data == lab) * vox
        if v0 > 1000.0:  # mm^3: every tissue class but specks
            assert v1 == pytest.approx(v0, rel=0.03), (lab, v0, v1)
    assert (out / "mri_biopsy.nii.gz").is_file()
    # the phantom's MR series is DICOM: the warped one too, in its frame of reference
    import pydicom

    first = [pydicom.dcmread(next(f.glob("*.dcm")), stop_before_pixels=True)
             for f in (PHANTOM / "mri" / "dicom", out / "mri_biopsy")]
    assert first[0].FrameOfReferenceUID == first[1].FrameOfReferenceUID
    assert first[0].SeriesInstanceUID != first[1].SeriesInstanceUID
    assert int(first[1].SeriesNumber) == int(first[0].SeriesNumber) + 1000
    # the simulated skin against its own warped label map (a cached run): the floor of the
    # comparison, the model's smoothed surface against the label map's voxel boundary
    # (measured 0.58 mm RMS); the landmarks against themselves: 0
    seen = out / "seen.csv"
    seen.write_text("name,x,y,z\n" + "".join(f"{r['name']},{r['compressed_x']},"
                                             f"{r['compressed_y']},{r['compressed_z']}\n"
                                             for r in rows[:2]))
    rc = main(["track", str(PHANTOM), "--view", "biopsy", "--landmarks", str(lm),
               "--compare-mri", str(out / "labels_biopsy.nii.gz"), "--compare-landmarks",
               str(seen), "--cache", str(cache), "--out", str(out), "--no-simulate"])
    assert rc == 0, capsys.readouterr().err
    cmp = json.loads((out / "compare_biopsy.json").read_text())
    assert 0 < cmp["surface_distance"]["rms_mm"] < 1.0
    assert [r["distance_mm"] for r in cmp["landmarks"]] == pytest.approx([0, 0], abs=2e-3)


def _check_biopsy_report(pdf, state, doc, rows):
    """The biopsy section (``biopsy.pdf``): a target page and a protocol page; the target
    table prints each point's compressed LPS position, displacement and 1-sigma (one
    decimal), the protocol table D and the plate gap of the summary."""
    import re

    import matplotlib.pyplot as plt

    from regtrack.report.biopsy import protocol_page, target_page
    from regtrack.pipeline.outputs import step_states
    from regtrack.report.fmt import num
    from regtrack.report.pdf import CaseReport, figure_text, render_pages
    from regtrack.tracking.compressed import map_points

    data = pdf.read_bytes()
    assert data[:5] == b"%PDF-" and len(re.findall(rb"/Type\s*/Page\b", data)) == 2
    fwd = map_points(state.dmap, [r["name"] for r in rows[:2]], [[float(r[f"mri_{a}"])
                                                                for a in "xyz"] for r in rows[:2]])
    fwd = dataclasses.replace(fwd, sigma_mm=np.array([p["sigma_mm"] for p in doc["points"][:2]]))
    rep = CaseReport("case", extra_pages=[target_page(state, [fwd], "case"),
                                          protocol_page(state, step_states(state.sim))])
    texts = []
    for fig in render_pages(rep):
        texts += figure_text(fig)
        plt.close(fig)
    for i in range(2):  # the same mapping as the command's: the same numbers
        assert ", ".join(num(v, 1) for v in fwd.mapped_lps_mm[i]) in texts
        assert {num(fwd.displacement_mm[i], 1), num(fwd.sigma_mm[i], 1)} <= set(texts)
    assert {"26.0", num(doc["compression"]["plate_gap_mm"], 1)} <= set(texts)
    assert "MR-guided biopsy: needle target, case case" in texts


def test_uncertainty_terms_from_a_surrogate_are_its_differences():
    """``--uncertainty --surrogate``: each term is the surrogate's difference added to the
    full simulation's nodes.  A surrogate whose field is a uniform translation linear in
    each parameter (a, b, c mm per unit of c1, nu, D; reproduced exactly by the fit) moves
    every mapped point by exactly that translation: the c1 term is |a| c1 c1_rel_sigma, the
    nu term |b| nu_sigma, the plate term |c| degree_sigma (1e-9 mm); c1 is the phantom's
    one composition c1.  Nothing is simulated (a state at the reference shape)."""
    from regtrack.case import load_case, resolve_configs
    from regtrack.surrogate import ParameterBox, fit_surrogate
    from regtrack.tracking.compressed import CompressedState
    from regtrack.tracking.deformation import DeformationMap
    from regtrack.tracking.sensitivity import point_sigma, surrogate_point
    from tests._models import coarse_model

    model = coarse_model(PHANTOM)
    a, b, c = np.array([1.0, -2.0, 0.5]), np.array([0.0, 30.0, 40.0]), np.array([-8.0, 6.0, 0.0])
    box = ParameterBox(("c1", "nu", "target_D"), (0.2, 0.45, 0.2), (2.0, 0.49, 0.5))
    pts = box.sample(6, seed=0)
    fields = np.array([np.tile(p[0] * a + p[1] * b + p[2] * c, (model.n_nodes, 1)) for p in pts])
    sur = fit_surrogate(pts, fields, names=box.names, lower=box.lower, upper=box.upper,
                        meta={"validation": {"view": "CC"}})
    state = CompressedState(None, "CC", DeformationMap.from_model(model, model.points, view="CC"),
                            {"D": 0.38}, model)
    lps = model.frame.to_patient(model.tumour_centroids()[1][None])
    ps = point_sigma(PHANTOM, state, ["t"], lps, surrogate=sur)
    cfg = resolve_configs(load_case(PHANTOM, deep=False))
    c1 = surrogate_point(cfg, state, sur)["c1"]
    assert ps.sources == {"c1": "surrogate", "nu": "surrogate", "plate": "surrogate"}
    tr = cfg.tracking
    np.testing.assert_allclose(ps.terms_mm["c1"], np.linalg.norm(a) * c1 * tr.c1_rel_sigma, rtol=1e-9)
    np.testing.assert_allclose(ps.terms_mm["nu"], np.linalg.norm(b) * tr.nu_sigma, rtol=1e-9)
    np.testing.assert_allclose(ps.terms_mm["plate"], np.linalg.norm(c) * tr.degree_sigma, rtol=1e-9)
