"""The CalculiX ground-truth pipeline's pieces (pipelines/make_truth_cases.py and
pipelines/bench_accuracy.py) without CalculiX or a regtrack run: the tet10 numbering and
its sub-tets, the quadratic embedding, the .dat parser, the rigid image map of the truth
(rotation sense), the outline of projected points, and the lesion matching of the bench.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

PIPE = Path(__file__).resolve().parents[1] / "pipelines"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, PIPE / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def mt():
    mod = _load("make_truth_cases")
    yield mod
    sys.modules.pop("make_truth_cases", None)


@pytest.fixture(scope="module")
def ba():
    mod = _load("bench_accuracy")
    yield mod
    sys.modules.pop("bench_accuracy", None)


def _tet10():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    mids = [0.5 * (x[a] + x[b]) for a, b in [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]]
    return np.vstack([x, mids]), np.arange(10)[None, :]


def test_shape_functions_reproduce_a_quadratic_field(mt):
    x, t = _tet10()
    u = np.column_stack([x[:, 0] ** 2, x[:, 0] * x[:, 1], 2 * x[:, 2]])  # exact in P2
    rng = np.random.default_rng(0)
    L = rng.dirichlet(np.ones(4), size=20)
    p = L[:, 1:] @ np.eye(3)  # barycentric -> point of the unit tet
    N = mt.shape10(L)
    assert np.allclose(N.sum(1), 1.0)
    got = N @ u[t[0]]
    want = np.column_stack([p[:, 0] ** 2, p[:, 0] * p[:, 1], 2 * p[:, 2]])
    assert np.allclose(got, want)
    # the embedding finds the element and gives the same displacement
    moved = mt.deform_points({"x": x, "tets": t}, u, p)
    assert np.allclose(moved - p, want)


def test_subtets_fill_the_element_and_orientation_fix(mt):
    x, t = _tet10()
    sub = t[:, mt.SUBTETS].reshape(-1, 4)
    v = mt.tet_volumes(x, np.pad(sub, ((0, 0), (0, 6))))
    assert np.all(v > 0) and np.isclose(v.sum(), 1 / 6)
    flipped = t.copy()
    flipped[:, [1, 2]] = flipped[:, [2, 1]]
    flipped[:, [4, 6]] = flipped[:, [6, 4]]
    flipped[:, [8, 9]] = flipped[:, [9, 8]]
    fixed = mt.fix_orientation(x, flipped)
    assert mt.tet_volumes(x, fixed)[0] > 0
    # after the fix the mid-side nodes still sit on their C3D10 edges
    for k, (a, b) in enumerate(mt.C3D10_EDGES):
        assert np.allclose(x[fixed[0, 4 + k]], 0.5 * (x[fixed[0, a]] + x[fixed[0, b]]))


def test_boundary_faces_of_one_tet_are_its_four_faces(mt):
    _, t = _tet10()
    faces = mt.boundary_faces(t)
    assert sorted(f for _, f, _ in faces) == [1, 2, 3, 4]


def test_parse_dat_takes_the_last_blocks(mt, tmp_path):
    dat = tmp_path / "r.dat"
    dat.write_text(
        "\n displacements (vx,vy,vz) for set NALL and time  0.5000000E+00\n\n"
        "         1  1.0E+00  0.0E+00  0.0E+00\n         2  0.0E+00  1.0E+00  0.0E+00\n\n"
        " forces (fx,fy,fz) for set NRUP and time  0.5000000E+00\n\n"
        "      9001  0.0E+00  0.0E+00 -1.0E+03\n\n"
        " displacements (vx,vy,vz) for set NALL and time  0.1000000E+01\n\n"
        "         1  2.0E+00  0.0E+00  0.0E+00\n         2  0.0E+00  3.0E+00  0.0E+00\n\n"
        " forces (fx,fy,fz) for set NRUP and time  0.1000000E+01\n\n"
        "      9001  0.0E+00  0.0E+00 -2.5E+03\n")
    u, f, t = mt.parse_dat(dat, 2)
    assert np.allclose(u, [[2, 0, 0], [0, 3, 0]]) and f == -2500.0 and t == 1.0


def test_body_force_unloads_prone_gravity_and_adds_standing(mt):
    # model frame x anterior, y superior: prone gravity +x is removed, standing -y added
    d, g = mt.body_force_direction(mt.model_basis("R"))
    assert g == pytest.approx(np.sqrt(2.0))
    assert np.allclose(d * g, [-1.0, -1.0, 0.0])


def test_plate_travel_follows_the_schedule(mt):
    # the upper plate's amplitude: HOLD of the way at T_G0, still until T_G1, then the rest
    assert mt.plate_travel(None) == 0.0
    assert mt.plate_travel(mt.T_G0) == pytest.approx(mt.HOLD)
    assert mt.plate_travel(0.5 * (mt.T_G0 + mt.T_G1)) == pytest.approx(mt.HOLD)
    assert mt.plate_travel(1.0) == pytest.approx(1.0)
    t = mt.T_G1 + 0.5 * (1.0 - mt.T_G1)
    assert mt.plate_travel(t) == pytest.approx(mt.HOLD + 0.5 * (1.0 - mt.HOLD))


def test_a_stopped_run_is_kept_only_when_the_plate_presses(mt):
    """Kept: gravity in full, T_ACCEPT of the travel and the upper plate pressing (19 L's
    MLO stopped at 74 % of the travel with 3.5e-24 mN, an uncompressed breast, and was
    kept before the force was checked)."""
    t = 0.95
    assert mt.plate_travel(t, "MLO") >= mt.T_ACCEPT
    assert mt.kept_early(t, -12624.8, "MLO")
    assert not mt.kept_early(t, -3.5e-24, "MLO")
    assert not mt.kept_early(t, None, "MLO")
    assert not mt.kept_early(0.1, -5000.0, "MLO")  # during gravity
    assert not mt.kept_early(None, -5000.0, "CC")


def test_rotation_sense_is_the_registrations(mt):
    from regtrack.registration.geometry import rotation

    for a in (-9.0, 0.0, 7.0):
        assert np.allclose(mt.rot(a), rotation(a))


def test_outline_and_centroid_of_a_projected_disc(mt):
    rng = np.random.default_rng(1)
    r = 40 * np.sqrt(rng.uniform(0, 1, 4000))
    a = rng.uniform(0, 2 * np.pi, 4000)
    rc = np.column_stack([200 + r * np.sin(a), 300 + r * np.cos(a)])
    outline, cen = mt.outline_from_points(rc, (500, 600), radius_px=3)
    assert np.allclose(cen, [200, 300], atol=1.0)
    assert mt.polygon_area(outline) == pytest.approx(np.pi * 43 ** 2, rel=0.1)
    # clipped by the image's edge: only the visible part counts
    outline2, cen2 = mt.outline_from_points(rc - [0, 290], (500, 600), radius_px=3)
    assert outline2[:, 1].min() >= 0 and cen2[1] > 10


def test_draws_are_in_the_issue_ranges(mt):
    for exam in ("03", "10", "11"):
        p = mt.draw_params(exam, "R", 52)
        assert 0.3 <= p["c1_kpa"]["fat"] <= 0.6 and 0.8 <= p["c1_kpa"]["gland"] <= 1.6
        assert 0.05 <= p["friction"] <= 0.2 and 40 <= p["mlo_angle_deg"] <= 60
        assert all(-10 <= v <= 10 for v in p["rotation_deg"].values())
        assert all(0.3 <= v <= 0.5 for v in p["D"].values()) and 650 <= p["sid_mm"] <= 660
    assert mt.draw_params("03", "R", 52) == mt.draw_params("03", "R", 52)


def test_bench_matches_the_lesion_on_the_mri_side(ba):
    lesions = [{"mri_lps_mm": [0, 0, 0], "centroid_px_rc": [1, 1]},
               {"mri_lps_mm": [50, 0, 0], "centroid_px_rc": [9, 9]}]
    m = ba.match_lesion(lesions, {"centroid_lps_mm": [48, 1, 0]})
    assert m["centroid_px_rc"] == [9, 9] and m["mri_match_mm"] == pytest.approx(np.hypot(2, 1))


def test_tracking_error_is_measured_to_the_lesion_centroid(ba):
    """The tracking error is taken to the truth lesion's projected volume centroid (the
    point regtrack predicts); the distance to the area centroid of the outline the image
    shows is reported beside it.  A lesion cut by the image edge: its visible outline's
    centroid lies 5 mm (50 px) from its own; a prediction 3 mm (30 px) from the lesion's
    centroid is 3 mm off, not 5.83 mm.  A truth file without the volume centroid falls
    back to the outline's."""
    tv = {"image_shape": [1000, 800], "pixel_mm": 0.1, "nipple_dicom_rc": [500.0, 100.0],
          "rotation_deg": 0.0, "tumours": [{"centroid_lps_mm": [0.0, 0.0, 0.0],
                                            "centroid_dicom_rc": [400.0, 750.0],
                                            "volume_centroid_projected_dicom_rc": [400.0, 800.0]}]}
    lesions = [{"mri_lps_mm": [1.0, 0.0, 0.0], "centroid_px_rc": [430.0, 800.0],
                "notes": ["partly beyond the image edge"]}]
    row = ba._tracking_columns(lesions, tv, "L", "")
    assert row["lesion_error_track_mm"] == pytest.approx(3.0)
    assert row["lesion_error_track_outline_mm"] == pytest.approx(np.hypot(3.0, 5.0))
    assert row["lesion_notes"] == "partly beyond the image edge"
    del tv["tumours"][0]["volume_centroid_projected_dicom_rc"]
    assert ba._tracking_columns(lesions, tv, "L", "")["lesion_error_track_mm"] == pytest.approx(np.hypot(3.0, 5.0))


@pytest.mark.parametrize("side", ["L", "R"])
def test_error_parts_remove_exactly_the_rotation_error(ba, side):
    """A prediction that is the true lesion turned about the nipple by the registration's
    rotation error (an exact model, a wrong theta) has no error left once that rotation is
    undone, whichever way the stored image is flipped; an offset along the chest wall ->
    nipple axis stays, with its sign."""
    from regtrack.phantom.dicom_mg import canonical_to_stored_rc
    from regtrack.registration.geometry import rotation

    px, shape = 0.1, (1000, 800)
    n_can = np.array([400.0, 700.0])   # canonical (row, col) px: nipple to the right
    t_can = np.array([520.0, 350.0])
    theta, theta_b = 6.0, 9.5          # truth rotation, registration's breast optimum

    def stored(rc):
        return canonical_to_stored_rc(rc, shape=shape, laterality=side).tolist()

    def turned(rc, deg):               # rotate canonical (row, col) about the nipple, y down
        xy = (rc - n_can)[::-1]
        return (rotation(deg) @ xy)[::-1] + n_can

    tv = {"image_shape": list(shape), "pixel_mm": px, "nipple_dicom_rc": stored(n_can),
          "rotation_deg": theta}
    tumour = {"centroid_dicom_rc": stored(t_can)}
    lesion = {"centroid_px_rc": stored(turned(t_can, theta_b - theta)), "theta_p_b_deg": theta_b}
    parts = ba.error_parts(lesion, tumour, tv, side)
    r = np.linalg.norm(t_can - n_can) * px
    assert parts["lesion_r_true_mm"] == pytest.approx(r)
    assert parts["lesion_error_true_theta_mm"] == pytest.approx(0.0, abs=1e-9)
    assert parts["theta_error_b_track_deg"] == pytest.approx(3.5)
    # 2 mm too far towards the nipple (canonical +x) after the rotation is undone
    lesion["centroid_px_rc"] = stored(turned(t_can + [0.0, 20.0], theta_b - theta))
    parts = ba.error_parts(lesion, tumour, tv, side)
    assert parts["lesion_error_x_mm"] == pytest.approx(2.0) and parts["lesion_error_y_mm"] == pytest.approx(0.0, abs=1e-9)
    # a nipple found 3 mm low (canonical +y) carries the whole prediction with it: with the
    # true nipple put back, only the 2 mm remain
    lesion["centroid_px_rc"] = stored(turned(t_can + [0.0, 20.0], theta_b - theta) + [30.0, 0.0])
    lesion["nipple_px_rc"] = stored(n_can + [30.0, 0.0])
    parts = ba.error_parts(lesion, tumour, tv, side)
    assert parts["nipple_error_mm"] == pytest.approx(3.0)
    assert parts["lesion_error_x_mm"] == pytest.approx(2.0) and parts["lesion_error_y_mm"] == pytest.approx(0.0, abs=1e-9)


def test_marked_case_gives_the_nipple_on_both_images(ba, tmp_path):
    """The 'track_marked' variant: the tracking case plus the truth's nipple, on the MRI
    (``[mri] nipple_lps_mm``) and on each mammogram (``[views.<V>] nipple_px``, DICOM row,
    col), and nothing else of the truth."""
    import tomllib

    src = tmp_path / "root" / "cases" / "pel07R_track"
    src.mkdir(parents=True)
    (src / "case.toml").write_text('[case]\nid = "pel07R_track"\n\n[mri]\nlabels = "mri/l.zip"\n'
                                   'side = "R"\n\n[views.CC]\nmammogram = "mammo/cc.dcm"\n')
    truth = {"mesh": {"nipple_lps_mm": [-60.0, -45.5, 12.25]},
             "views": {"CC": {"nipple_dicom_rc": [812.5, 40.0], "tumours": [{"centroid_dicom_rc": [1, 2]}]}}}
    dst = ba.marked_case(tmp_path / "root", "pel07R", truth, tmp_path / "out" / "pel07R_track_marked")
    doc = tomllib.loads((dst / "case.toml").read_text())
    assert doc["case"]["id"] == "pel07R_track_marked"
    assert doc["mri"]["nipple_lps_mm"] == [-60.0, -45.5, 12.25] and doc["mri"]["side"] == "R"
    assert doc["views"]["CC"] == {"nipple_px": [812.5, 40.0], "mammogram": "mammo/cc.dcm"}
    assert "tumour_polygon" not in (dst / "case.toml").read_text()


def test_marked_unrotated_copy_takes_the_unrotated_nipple(ba, tmp_path):
    """'paper_rot0_marked': the nipple of the unrotated DICOM (``views_rot0``), not of the
    rotated one, and the tumour outline of the paper case kept."""
    import tomllib

    src = tmp_path / "root" / "cases" / "pel07R_paper_rot0"
    src.mkdir(parents=True)
    (src / "case.toml").write_text('[case]\nid = "pel07R_paper_rot0"\n\n[mri]\nlabels = "mri/l.zip"\n\n'
                                   '[views.CC]\nmammogram = "mammo/cc.dcm"\n'
                                   'tumour_polygon = "mammo/cc_tumour.json"\n')
    truth = {"mesh": {"nipple_lps_mm": [-60.0, -45.5, 12.25]},
             "views": {"CC": {"nipple_dicom_rc": [812.5, 40.0]}},
             "views_rot0": {"CC": {"nipple_dicom_rc": [800.0, 35.5]}}}
    dst = ba.marked_case(tmp_path / "root", "pel07R", truth, tmp_path / "out" / "pel07R_paper_rot0_marked",
                         "paper_rot0")
    doc = tomllib.loads((dst / "case.toml").read_text())
    assert doc["case"]["id"] == "pel07R_paper_rot0_marked"
    assert doc["views"]["CC"] == {"nipple_px": [800.0, 35.5], "mammogram": "mammo/cc.dcm",
                                  "tumour_polygon": "mammo/cc_tumour.json"}


def test_model_sensitivity_is_the_quadrature_of_the_measured_moves(ba):
    """The sensitivity variants: c1 moved the lesion 3 mm, nu 4 mm, so the measured model
    shift is 5 mm and alpha = 5 / |Delta| (|Delta| = 10 mm); a lesion a variant lost is
    reported without a total."""
    base = [{"lesion": 1, "centroid_mm": [10.0, 20.0], "inplane_shift_mm": 10.0,
             "uncertainty_terms_mm": {"model": 1.0}},
            {"lesion": 2, "centroid_mm": [0.0, 0.0], "inplane_shift_mm": 4.0,
             "uncertainty_terms_mm": {"model": 0.4}}]
    moved = {"c1": [{"lesion": 1, "centroid_mm": [13.0, 20.0]}, {"lesion": 2, "centroid_mm": [0.0, 1.0]}],
             "nu": [{"lesion": 1, "centroid_mm": [10.0, 24.0]}]}
    r1, r2 = ba.model_sensitivity(base, moved)
    assert r1["shift_c1_mm"] == pytest.approx(3.0) and r1["shift_nu_mm"] == pytest.approx(4.0)
    assert r1["model_shift_mm"] == pytest.approx(5.0) and r1["alpha_measured"] == pytest.approx(0.5)
    assert r1["sigma_model_mm"] == 1.0
    assert r2["shift_c1_mm"] == pytest.approx(1.0) and r2["shift_nu_mm"] is None
    assert "model_shift_mm" not in r2 and "alpha_measured" not in r2


def test_sensitivity_sets_are_the_trackers_one_sigma_moves(ba, tmp_path):
    """The variants move c1 by (1 + c1_rel_sigma) and nu by -nu_sigma of the case's own
    settings, as ``regtrack track --uncertainty`` does."""
    case = tmp_path / "c"
    case.mkdir()
    (case / "l.zip").write_bytes(b"")
    (case / "case.toml").write_text('[case]\nid = "c"\n\n[mri]\nlabels = "l.zip"\nscheme = "pelicano-simple"\n\n'
                                    '[mechanics]\ntissue_c1_kpa = 1.0\nnu = 0.45\n\n'
                                    '[tracking]\nc1_rel_sigma = 0.5\nnu_sigma = 0.05\n')
    assert ba.sensitivity_sets(case, "track_c1") == ["mechanics.tissue_c1_kpa=1.5"]
    assert ba.sensitivity_sets(case, "track_nu") == ["mechanics.nu=0.4"]


def test_band_table_averages_each_band_and_the_difference(ba):
    """Two points 10 mm and one 50 mm from the chest wall: per band, each model's mean
    displacement and the mean / RMS of regtrack - truth."""
    ant = np.array([5.0, 15.0, 50.0])
    ut = np.array([[0.0, 0, 0], [0, 0, 0], [1, 2, 3]])
    ur = np.array([[3.0, 0, 0], [0, 4, 0], [1, 2, 3]])
    rows = ba.band_table(ant, ut, ur)
    assert [r["band_mm"] for r in rows] == [(0.0, 20.0), (40.0, 60.0)]
    assert rows[0]["n"] == 2 and np.allclose(rows[0]["mean_diff"], [1.5, 2.0, 0.0])
    assert rows[0]["rms_diff"] == pytest.approx(np.sqrt((9 + 16) / 2))
    assert rows[1]["n"] == 1 and rows[1]["rms_diff"] == 0.0 and np.allclose(rows[1]["u_truth"], [1, 2, 3])


def test_collect_keeps_only_the_view_asked_for(ba, tmp_path):
    """``--views CC``: a truth with both views gives rows for the CC only (an MLO truth that
    is not usable stays out of the table), and without it both views."""
    sim = {"gap_mm": 60.0, "angle_deg": 0.0}
    view = {"rotation_deg": 2.0, "simulation": sim, "tumours": [], "nipple_dicom_rc": [10, 10]}
    truth = {"side": "R", "params": {"friction": 0.1, "D": {"CC": 0.4, "MLO": 0.3}},
             "views": {"CC": view, "MLO": view}}
    assert [r["view"] for r in ba.collect(tmp_path, "pelX", truth, tmp_path, "CC")] == ["CC"]
    assert [r["view"] for r in ba.collect(tmp_path, "pelX", truth, tmp_path)] == ["CC", "MLO"]


def test_remeshed_surface_fallback_fills_a_cut_ball(mt):
    """The meshing fallback (an isotropically remeshed surface that gmsh fills as it is) on
    a half ball of radius 30 mm, cut flat like a breast at its chest wall: the remeshing
    keeps the marching-cubes volume (restored to 0.5 %), the tet10 fill has that volume
    (1 %: the same triangles bound it), positive elements and mid-side nodes on their edges,
    and the volume is the half ball's within 5 % (marching cubes of a smoothed 1 mm mask)."""
    r = 30.0
    g = np.indices((72, 72, 40)).astype(float) + 0.5
    c = np.array([36.0, 36.0, 4.0])
    mask = (np.linalg.norm(g - c[:, None, None, None], axis=0) <= r) & (g[2] >= c[2])
    geo = {"mask": mask, "affine": np.eye(4), "spacing": np.ones(3)}
    pts, faces = mt.surface_from_mask(geo, sigma=1.0)
    v_mc = abs(float(np.einsum("ij,ij->i", pts[faces[:, 0]],
                               np.cross(pts[faces[:, 1]], pts[faces[:, 2]])).sum()) / 6.0)
    size = 12.0
    sv, sf = mt.remeshed_surface(pts, faces, size)
    v_rm = abs(float(np.einsum("ij,ij->i", sv[sf[:, 0]], np.cross(sv[sf[:, 1]], sv[sf[:, 2]])).sum()) / 6.0)
    assert abs(v_rm / v_mc - 1) < 0.005
    x, tets = mt.gmsh_tet10(sv, sf, size, reparametrise=False)
    tets = mt.fix_orientation(x, tets)
    vol = mt.tet_volumes(x, tets)
    assert vol.min() > 0
    assert abs(vol.sum() / v_mc - 1) < 0.01
    assert abs(vol.sum() / (2 / 3 * np.pi * r**3) - 1) < 0.05
    for k, (a, b) in enumerate(mt.C3D10_EDGES):
        assert np.allclose(x[tets[:, 4 + k]], 0.5 * (x[tets[:, a]] + x[tets[:, b]]))


def test_a_failed_view_is_run_on_the_refined_mesh(mt, tmp_path, monkeypatch):
    """simulate_view: a view CalculiX cannot finish on the base mesh is run on the mesh of
    the next level in its own folder; when every level fails, the error names each."""
    meshes = {k: ({"n_tets": 1000 * 2**k}, [], {}) for k in range(mt.REFINE_LEVELS + 1)}
    calls = []

    def fake(work, mesh, view, side, p, timeout, ok=frozenset({2000})):
        calls.append((work, mesh["n_tets"]))
        if mesh["n_tets"] not in ok:
            raise RuntimeError(f"ccx {view} failed (rc 201)\nlog tail")
        return {"gap_mm": 50.0}

    monkeypatch.setattr(mt, "run_ccx", fake)
    sim, level = mt.simulate_view(tmp_path, meshes.__getitem__, "MLO", "R", {}, 10)
    assert level == 1 and sim == {"gap_mm": 50.0}
    assert calls == [(tmp_path, 1000), (tmp_path / "refined1", 2000)]
    assert (tmp_path / "refined1").is_dir()
    monkeypatch.setattr(mt, "run_ccx", lambda *a: fake(*a, ok=frozenset()))
    with pytest.raises(RuntimeError, match=r"1000 elements: ccx MLO failed .*; 2000 elements: ccx MLO"):
        mt.simulate_view(tmp_path, meshes.__getitem__, "MLO", "R", {}, 10)
