"""Tracking through the project's own virtual projection and registration (issue 9).

A gmsh hemisphere with a spherical tumour is "compressed" by known affine maps (no
solver), projected by :func:`regtrack.virtual.project.project_model`, and a *real* view
is made from the virtual one by a known rigid in-plane motion (rotation about the
nipple + shift).  The real registration (:func:`regtrack.registration.align`) then has
to recover that motion; tracking must put the tumour where the motion puts it.
Tolerances: the golden-section search stops at 1e-3 deg, i.e. < 1e-4 mm at 100 mm from
the nipple, and both contours are the same polylines, so 0.05 mm is generous.
Outputs (JSON, PNG overlays, PDF section) and the CLI's error paths are checked too.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from regtrack.errors import TrackingError
from regtrack.model.types import AnatomicalFrame
from regtrack.registration import align
from regtrack.tracking import InPlane, PredictionUncertainty, Residual, TrackingConfig, ViewMap
from regtrack.tracking.figures import report_section, write_outputs
from regtrack.tracking.session import TrackingSession
from regtrack.tracking.track import parse_label, track_case
from regtrack.views import MammogramView
from regtrack.virtual.config import VirtualConfig
from regtrack.virtual.project import default_frame, project_model

MOTION = {"CC": (6.0, np.array([40.0, 75.0])), "MLO": (-5.0, np.array([45.0, 80.0]))}
MAPS = {"CC": (np.diag([1.2, 0.55, 1.25]), np.array([0.0, -5.0, 0.0])),
        "MLO": (np.array([[1.2, 0.0, 0.0], [0.0, 0.85, -0.25], [0.0, -0.25, 0.95]]), np.zeros(3))}


def R2(deg):
    t = np.deg2rad(deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


class _Case:
    id = "synthetic"
    toml_path = "synthetic/case.toml"


@pytest.fixture(scope="module")
def session():
    from regtrack.mechanics.meshes import hemisphere_model

    m = hemisphere_model(50.0, 6.0, tumour_radius=9.0)
    # model frame: origin at the nipple (the pole), x anterior
    m.points = m.points - m.points[m.nipple]
    m.frame = AnatomicalFrame.standard("R", origin_lps=(-90.0, -40.0, 0.0))
    views, truth = {}, {}
    for v, (A, b) in MAPS.items():
        pos = m.points @ A.T + b
        vm = project_model(m, pos, view=v, config=VirtualConfig(render=False),
                           frame=default_frame(pos, v, "R"))
        th, n_p = MOTION[v]
        n_v = vm.view.nipple

        def move(xy, th=th, n_p=n_p, n_v=n_v):
            return (np.asarray(xy) - n_v) @ R2(th).T + n_p
        real = MammogramView(v, "R", move(vm.view.breast_contour), n_p,
                             [move(t) for t in vm.view.tumour_contours], source=f"real {v}")
        al = align(real, vm.view)
        unc = PredictionUncertainty.from_alignment(al, real, D=0.4, sigma_D=0.0,
                                                   config=TrackingConfig())
        views[v] = ViewMap(v, pos, vm.frame, InPlane.from_alignment(al), None, None,
                           Residual.from_alignment(al), real, unc)
        views[v]._alignment = al
        truth[v] = move
    s = TrackingSession(_Case(), m, views)
    s._truth_motion = truth
    return s


def test_inplane_matches_the_alignment(session):
    rng = np.random.default_rng(0)
    for v, vm in session.views.items():
        al = vm._alignment
        xy = rng.uniform(-80, 80, (50, 2))
        assert np.allclose(vm.inplane.to_real(xy), al.transform(xy), atol=1e-12)
        assert np.allclose(vm.inplane.to_virtual(vm.inplane.to_real(xy)), xy, atol=1e-9)
        assert al.theta_p == pytest.approx(MOTION[v][0], abs=2e-3)
        # identical contours: the residual is (almost) zero everywhere
        assert vm.residual.distances.max() < 0.05


def test_tumour_lands_where_the_motion_puts_it(session):
    res = track_case(session, label="tumour")
    centre = np.array([25.0, 0.0, 0.0]) - np.array([50.0, 0.0, 0.0])   # tumour at r/2 from the wall
    assert np.linalg.norm(res.mri.reference_mm - centre) < 0.3           # faceted sphere
    for v, p in res.mri.views.items():
        A, b = MAPS[v]
        vm = session.views[v]
        expect = session._truth_motion[v](vm.to_virtual((A @ res.mri.reference_mm + b)[None])[0])
        assert np.linalg.norm(p.xy_mm - expect) < 0.05
        # the projected outline's area centroid agrees with the projected mass centroid
        # for this symmetric tumour (to the mesh's faceting)
        assert np.linalg.norm(p.outline_centroid_mm - p.xy_mm) < 0.5
        # identical contours: the residual floor (0.5 mm) and no rotation uncertainty; the
        # model term alpha |Delta|, Delta = P (A - I) (c - nipple) in the plate's axes
        P = (np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]) if v == "CC"
             else np.array([[1.0, 0.0, 0.0], [0.0, -1.0, -1.0]]) / [[1.0], [np.sqrt(2.0)]])
        delta = np.linalg.norm(P @ (A - np.eye(3)) @ res.mri.reference_mm)  # nipple at 0
        t = p.terms_mm
        assert t["registration_residual"] < 0.05 and t["rotation"] < 0.05 and t["nipple"] == 0
        assert t["model"] == pytest.approx(TrackingConfig().material_rel * delta, rel=1e-9)
        assert p.sigma_mm == pytest.approx(np.sqrt(0.5 ** 2 + t["rotation"] ** 2 + t["model"] ** 2),
                                           rel=1e-12)


def test_cc_point_on_the_tumour_gives_an_mlo_curve_through_it(session):
    tum = track_case(session, label="tumour")
    cc_xy = tum.mri.views["CC"].xy_mm
    res = track_case(session, view_points={"CC": cc_xy}, view_points_mm=True,
                     truth={"MLO": tum.mri.views["MLO"].xy_mm})
    seg = res.segments[0]
    assert (seg.source_view, seg.target_view) == ("CC", "MLO")
    # the ray through the tumour centre's CC image passes through that centre (the CC map
    # keeps vertical lines vertical), so the MLO curve passes through its MLO image
    assert seg.truth_distance_mm < 0.1
    assert seg.most_likely["reference_distance_mm"] < 0.2
    assert seg.most_likely["truth_distance_mm"] < 0.3
    assert "tumour 1" in seg.most_likely["lesion"]
    # ray length = compressed thickness of the hemisphere at that point
    assert 20.0 < seg.thickness_mm < 0.55 * 100.0 + 1.0


def test_outputs_and_report_section(session, tmp_path):
    cc_nip = session.views["CC"].real.nipple
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    res = track_case(session, label="tumour", view_points={"CC": cc_nip - np.array([30.0, 0.0])},
                     view_points_mm=True,
                     view_contours={"CC": cc_nip + np.c_[-30 + 4 * np.cos(t), 4 * np.sin(t)]})
    reals = {v: vm.real for v, vm in session.views.items()}
    paths = write_outputs(res, tmp_path, reals=reals)
    names = sorted(p.name for p in paths)
    assert names == ["track_cc.png", "track_mlo.png", "tracking.json", "tracking.pdf"]
    doc = json.loads((tmp_path / "tracking.json").read_text())
    assert doc["mri"]["views"]["CC"]["xy_mm"] == pytest.approx(res.mri.views["CC"].xy_mm.tolist())
    assert doc["segments"][0]["length_mm"] > 10
    assert doc["contours"]["CC"]["target_view"] == "MLO" and len(doc["contours"]["CC"]["curves"]) == 12
    assert all((tmp_path / n).stat().st_size > 10_000 for n in names if n.endswith((".png", ".pdf")))
    sec = report_section(res)
    assert sec["title"].startswith("Lesion tracking") and any("curve of" in ln for ln in sec["lines"])


def test_bad_requests(session):
    with pytest.raises(TrackingError, match="nothing to track"):
        track_case(session)
    with pytest.raises(TrackingError, match="tumour:K"):
        parse_label("lesion")
    assert parse_label("tumour:2") == ("tumour", 2) and parse_label("-3") == ("label", -3)
    with pytest.raises(TrackingError, match="outside the breast on the real CC"):
        track_case(session, view_points={"CC": (-50.0, 300.0)}, view_points_mm=True)
    with pytest.raises(TrackingError, match="unknown view 'ap'"):
        session.view("ap")


def _tiny_case(tmp_path):
    """A case folder with a label map and CC/MLO DICOMs (contents irrelevant: never simulated)."""
    import shutil

    from regtrack.imaging.mammogram.synthetic import synthetic_breast, write_dicom
    from tests.conftest import SAMPLE_CASES

    (tmp_path / "mri").mkdir(parents=True)
    shutil.copy(SAMPLE_CASES / "phantom01" / "mri" / "labels.nii.gz", tmp_path / "mri" / "labels.nii.gz")
    img = synthetic_breast(label=False).image
    for v in ("cc", "mlo"):
        write_dicom(tmp_path / f"{v}.dcm", img * 4000, ImageLaterality="R", ViewPosition=v.upper(),
                    PixelSpacing=[0.25, 0.25], PatientOrientation=["P", "L"] if v == "cc" else ["P", "FL"])
    (tmp_path / "case.toml").write_text(
        '[case]\nid = "tiny"\n[mri]\nlabels = "mri/labels.nii.gz"\nscheme = "pelicano-detailed"\n'
        'side = "R"\n[views.CC]\nmammogram = "cc.dcm"\n[views.MLO]\nmammogram = "mlo.dcm"\n')
    return tmp_path


def test_cli_errors(tmp_path, capsys):
    from regtrack.cli import main

    case = _tiny_case(tmp_path / "case")
    cache = tmp_path / "cache"
    rc = main(["track", str(case), "--label", "tumour", "--no-simulate", "--cache", str(cache)])
    err = capsys.readouterr().err
    assert rc == 2 and "not simulated yet" in err and "regtrack run" in err and "mesh" in err
    rc = main(["track", str(case), "--label", "tumour", "--views", "CC,AP", "--cache", str(cache)])
    assert rc == 2 and "unknown view 'AP'" in capsys.readouterr().err
    rc = main(["track", str(case), "--mri-point", "1", "2", "3", "--label", "tumour"])
    assert rc == 2 and "not both" in capsys.readouterr().err
    assert not cache.exists() or not any(cache.rglob("_complete.json"))   # nothing was run
