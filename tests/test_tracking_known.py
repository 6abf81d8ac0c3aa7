"""Known-geometry tests of the tracking chain (issue 9): no simulation, exact answers.

The "simulations" are affine maps of a box mesh (a rigid rotation for CC, a compression
with shear and rotation for MLO).  A P1 mesh reproduces an affine map exactly, so the
located material points, their deformed positions, the plate projection, the in-plane
registration and the pixel conversion can all be checked against closed-form formulas
written out independently here (plate axes of a right breast: CC ``(X, Y) = (x, -z)``;
MLO at 45 deg ``(X, Y) = (x, -(y + z)/sqrt 2)``, up to the plate origin along ``n``).
Tolerances: 1e-9 mm (round-off) unless stated.
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import TrackingError
from regtrack.imaging.mammogram.orient import Orientation
from regtrack.mechanics.meshes import box_model
from regtrack.model.types import TUMOUR, AnatomicalFrame
from regtrack.tracking import (InPlane, PixelFrame, PredictionUncertainty, Residual, TetLocator,
                               TrackingConfig, ViewMap, track_mri_point, track_tumour,
                               track_view_point)
from regtrack.virtual.project import default_frame

SQ2 = np.sqrt(2.0)
LPS_ORIGIN = np.array([10.0, 20.0, 30.0])


def rot(axis: int, deg: float) -> np.ndarray:
    t = np.deg2rad(deg)
    c, s = np.cos(t), np.sin(t)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def R2(deg: float) -> np.ndarray:
    t = np.deg2rad(deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


# CC: a rigid rotation + translation; MLO: compression, shear and a rotation about x
A_CC, B_CC = rot(1, 8.0) @ rot(0, -5.0), np.array([2.0, -3.0, 1.0])
A_MLO = rot(0, 12.0) @ np.array([[1.15, 0.1, 0.0], [0.0, 0.65, 0.05], [0.0, 0.0, 1.25]])
B_MLO = np.array([-1.0, 4.0, 2.5])
BOX_LO, BOX_LEN = np.array([-60.0, -40.0, -50.0]), np.array([60.0, 80.0, 100.0])

INPLANE = {"CC": InPlane(np.array([80.0, 60.0]), np.array([-2.0, 5.0]), 4.0, 2.5, 5.5),
           "MLO": InPlane(np.array([95.0, 70.0]), np.array([1.0, -3.0]), -7.0, -6.0, -8.0)}
SHAPE = (2000, 1500)   # DICOM rows, cols
SPACING = np.array([0.1, 0.08])


@pytest.fixture(scope="module")
def model():
    m = box_model(tuple(BOX_LEN), (6, 8, 10), origin=tuple(BOX_LO))
    m.frame = AnatomicalFrame.standard("R", origin_lps=LPS_ORIGIN)
    c = m.points[m.tets].mean(1)
    tum = np.linalg.norm(c - np.array([-25.0, 5.0, 10.0]), axis=1) < 14.0
    m.region = np.where(tum, TUMOUR, 1)
    m.tumour_id = tum.astype(int)
    return m


#: the uncertainty model's inputs of each view: no residual samples (the floor applies),
#: an angular 1-sigma (deg), D and its 1-sigma, the nipple run u (mm)
UNCERTAINTY = {"CC": (0.8, 0.40, 0.02, 3.0), "MLO": (1.5, 0.30, 0.03, 0.0)}


def _viewmap(model, view):
    A, b = (A_CC, B_CC) if view == "CC" else (A_MLO, B_MLO)
    pos = model.points @ A.T + b
    px = PixelFrame(SPACING, Orientation(SHAPE, False, True, False, "test: right breast"))
    th, D, sD, u = UNCERTAINTY[view]
    unc = PredictionUncertainty(Residual(np.zeros((0, 2)), np.zeros(0)), INPLANE[view].nipple,
                                th, D, sD, u, TrackingConfig())
    return ViewMap(view, pos, default_frame(pos, view, "R"), INPLANE[view], px, uncertainty=unc)


def expected_sigma(model, view: str, q_model: np.ndarray, r: np.ndarray) -> float:
    """The four terms in closed form: the floor, r sigma_theta, |Delta| sqrt((sD/D)^2 +
    alpha^2) with Delta = P (A - I) (q - nipple) (P the plate's in-plane axes) and u / sqrt 3."""
    A = A_CC if view == "CC" else A_MLO
    P = (np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]) if view == "CC"
         else np.array([[1.0, 0.0, 0.0], [0.0, -1.0 / SQ2, -1.0 / SQ2]]))
    delta = np.linalg.norm(P @ (A - np.eye(3)) @ (q_model - model.points[model.nipple]))
    th, D, sD, u = UNCERTAINTY[view]
    cfg = TrackingConfig()
    rot_term = np.linalg.norm(r - INPLANE[view].nipple) * np.deg2rad(th)
    model_term = delta * np.hypot(sD / D, cfg.material_rel)
    return float(np.sqrt(cfg.min_residual_mm ** 2 + rot_term ** 2 + model_term ** 2 + u ** 2 / 3))


@pytest.fixture(scope="module")
def views(model):
    return {v: _viewmap(model, v) for v in ("CC", "MLO")}


def expected_px(view: str, p_def: np.ndarray, hmin: float):
    """Closed-form chain: plate projection, registration, pixels (flip left-right)."""
    if view == "CC":
        v = np.array([p_def[0], -p_def[2]])
    else:
        v = np.array([p_def[0], -(p_def[1] + p_def[2]) / SQ2])
    ip = INPLANE[view]
    r = ip.nipple + R2(ip.theta_deg) @ (v - ip.virtual_nipple)
    row, col = r[1] / SPACING[0], r[0] / SPACING[1]
    return v, r, np.array([row, (SHAPE[1] - 1) - col])


def test_mri_point_maps_exactly(model, views):
    q_model = np.array([-20.0, 12.0, -7.0])
    q_lps = model.frame.to_patient(q_model)
    # standard frame: x anterior = -P, y superior = +S, z right = -L
    assert np.allclose(q_lps, LPS_ORIGIN + [7.0, 20.0, 12.0])
    res = track_mri_point(model, views, q_lps)
    assert np.allclose(res.reference_mm, q_model, atol=1e-9)
    for view, (A, b) in (("CC", (A_CC, B_CC)), ("MLO", (A_MLO, B_MLO))):
        pred = res.views[view]
        p_def = A @ q_model + b
        assert np.allclose(pred.deformed_mm, p_def, atol=1e-9)
        hmin = views[view].height_range()[0]
        v, r, px = expected_px(view, p_def, hmin)
        assert np.allclose(pred.virtual_mm, v, atol=1e-9)
        assert np.allclose(pred.xy_mm, r, atol=1e-9)
        assert np.allclose(pred.px, px, atol=1e-9)
        # round trip of the pixel frame
        assert np.allclose(views[view].pixels.px_to_mm(pred.px), r, atol=1e-9)
        # uncertainty: the four terms of regtrack.tracking.uncertainty in closed form
        assert pred.sigma_mm == pytest.approx(expected_sigma(model, view, q_model, r), rel=1e-9)
        assert set(pred.terms_mm) == {"registration_residual", "rotation", "model", "nipple"}


def test_tumour_mass_centroid_follows_the_affine_map(model, views):
    res = track_tumour(model, views)
    sel = model.region == TUMOUR
    x = model.points[model.tets[sel]]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]))
    c_ref = (vol[:, None] * x.mean(1)).sum(0) / vol.sum()
    assert np.allclose(res.reference_mm, c_ref, atol=1e-9)
    for view, (A, b) in (("CC", (A_CC, B_CC)), ("MLO", (A_MLO, B_MLO))):
        pred = res.views[view]
        assert np.allclose(pred.deformed_mm, A @ c_ref + b, atol=1e-9)
        _, r, _ = expected_px(view, A @ c_ref + b, 0.0)
        assert np.allclose(pred.xy_mm, r, atol=1e-9)
        # the projected outline surrounds the predicted centroid
        from shapely.geometry import Point, Polygon

        assert Polygon(pred.outline_mm).contains(Point(*pred.xy_mm))


def _material_ray(x_real, hmin):
    """Closed-form material line under a real CC point: p'(h) = (X, hmin + h, -Y)."""
    ip = INPLANE["CC"]
    v = ip.virtual_nipple + R2(-ip.theta_deg) @ (x_real - ip.nipple)

    def material(h):
        p_def = np.array([v[0], hmin + h, -v[1]])
        return A_CC.T @ (p_def - B_CC)
    return material


def _box_interval(material) -> tuple[float, float]:
    """Heights where the material line is inside the box (slab method)."""
    q0, d = material(0.0), material(1.0) - material(0.0)
    lo, hi = -np.inf, np.inf
    for k in range(3):
        if abs(d[k]) < 1e-12:   # parallel to these faces: must lie between them
            assert BOX_LO[k] < q0[k] < BOX_LO[k] + BOX_LEN[k]
            continue
        a = (BOX_LO[k] - q0[k]) / d[k]
        b = (BOX_LO[k] + BOX_LEN[k] - q0[k]) / d[k]
        lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
    return lo, hi


def test_cc_point_to_mlo_segment_exact(model, views):
    cc, mlo = views["CC"], views["MLO"]
    x_real = np.array([70.0, 55.0])
    hmin = cc.positions[:, 1].min()   # CC lower plate: y = lowest deformed node
    material = _material_ray(x_real, hmin)
    h_in, h_out = _box_interval(material)
    h_star = 0.4 * h_in + 0.6 * h_out
    q_star = material(h_star)
    _, truth, _ = expected_px("MLO", A_MLO @ q_star + B_MLO, 0.0)
    cfg = TrackingConfig(ray_step_mm=0.2)
    px = cc.pixels.mm_to_px(x_real)
    seg = track_view_point(model, cc, mlo, px, config=cfg, lesion_reference_mm=q_star,
                           truth_mm=truth)
    assert np.allclose(seg.source_mm, x_real, atol=1e-9)
    assert len(seg.parts) == 1
    # every vertex is the closed-form image of its ray sample
    for h, ref, xy, rc in zip(seg.heights_mm, seg.reference_mm, seg.polyline_mm, seg.polyline_px):
        q = material(h)
        assert np.allclose(ref, q, atol=1e-9)
        _, r, p = expected_px("MLO", A_MLO @ q + B_MLO, 0.0)
        assert np.allclose(xy, r, atol=1e-9) and np.allclose(rc, p, atol=1e-9)
    # end points: the first/last samples inside the box, within one ray step of the faces
    assert h_in - 1e-9 <= seg.heights_mm[0] <= h_in + cfg.ray_step_mm
    assert h_out - cfg.ray_step_mm <= seg.heights_mm[-1] <= h_out + 1e-9
    # length of the (straight) image of the segment, up to the two end samples
    _, r_in, _ = expected_px("MLO", A_MLO @ material(h_in) + B_MLO, 0.0)
    _, r_out, _ = expected_px("MLO", A_MLO @ material(h_out) + B_MLO, 0.0)
    rate = np.linalg.norm(r_out - r_in) / (h_out - h_in)   # mm of image per mm of height
    assert seg.length_mm == pytest.approx(np.linalg.norm(r_out - r_in), abs=2 * cfg.ray_step_mm * rate)
    assert seg.thickness_mm == pytest.approx(h_out - h_in, abs=2 * cfg.ray_step_mm)
    # the truth lies on the curve; the most likely point is the nearest sample to it
    assert seg.truth_distance_mm < 1e-6
    ml = seg.most_likely
    assert ml["reference_distance_mm"] <= cfg.ray_step_mm / 2 + 1e-9   # rigid CC: unit speed
    assert ml["truth_distance_mm"] <= cfg.ray_step_mm / 2 * rate + 1e-9
    assert abs(ml["height_mm"] - h_star) <= cfg.ray_step_mm / 2 + 1e-9


def test_mlo_point_back_to_cc(model, views):
    """MLO -> CC inverts CC -> MLO: the CC point lies on the predicted CC curve."""
    cc, mlo = views["CC"], views["MLO"]
    x_cc = np.array([70.0, 55.0])
    seg = track_view_point(model, cc, mlo, x_cc, pixels=False)
    k = len(seg.polyline_mm) // 2
    back = track_view_point(model, mlo, cc, seg.polyline_mm[k], pixels=False, truth_mm=x_cc)
    assert back.truth_distance_mm < 1e-6


def test_locator_is_exact_and_finds_outside_points(model):
    loc = TetLocator(model.points, model.tets)
    rng = np.random.default_rng(3)
    q = rng.uniform(BOX_LO - 10, BOX_LO + BOX_LEN + 10, (3000, 3))
    inside = np.all((q >= BOX_LO) & (q <= BOX_LO + BOX_LEN), axis=1)
    got = loc.locate(q)
    assert np.array_equal(got.inside, inside)
    assert np.allclose(got.subset(inside).interpolate(model.tets, model.points), q[inside], atol=1e-9)
    assert (got.bary[inside] >= -1e-9).all()


def test_bad_inputs(model, views):
    with pytest.raises(TrackingError, match=r"outside the breast model .* LPS mm"):
        track_mri_point(model, views, model.frame.to_patient([30.0, 0.0, 0.0]))
    with pytest.raises(TrackingError, match="not finite"):
        track_mri_point(model, views, [np.nan, 0, 0])
    with pytest.raises(TrackingError, match="outside the 2000x1500 px image"):
        track_view_point(model, views["CC"], views["MLO"], (2500.0, 10.0))
    with pytest.raises(TrackingError, match="misses the simulated breast"):
        track_view_point(model, views["CC"], views["MLO"], (400.0, 10.0), pixels=False)
    with pytest.raises(TrackingError, match="no tumour 3"):
        track_tumour(model, views, tumour=3)


def test_point_just_outside_is_snapped_and_recorded(model, views):
    q = np.array([0.8, 0.0, 0.0])   # 0.8 mm in front of the anterior face x = 0
    res = track_mri_point(model, views, model.frame.to_patient(q))
    assert any("snapped" in n for n in res.notes)
    assert np.linalg.norm(res.views["CC"].deformed_mm - (A_CC @ [0.0, 0.0, 0.0] + B_CC)) < 1.0


def test_voxel_region_centroid_is_mapped_exactly(model, views):
    """Mean of mapped voxel centres = affine image of their mean (equal masses)."""
    from regtrack.tracking import track_points_region

    g = np.stack(np.meshgrid(*[np.arange(-5.0, 5.1, 1.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts_model = g + np.array([-30.0, 0.0, 5.0])
    res = track_points_region(model, views, model.frame.to_patient(pts_model), description="cube")
    c = pts_model.mean(0)
    assert res.n_points == len(g) and np.allclose(res.reference_mm, c, atol=1e-9)
    for view, (A, b) in (("CC", (A_CC, B_CC)), ("MLO", (A_MLO, B_MLO))):
        assert np.allclose(res.views[view].deformed_mm, A @ c + b, atol=1e-9)


def test_residual_term_is_local():
    """sigma_res is the RMS residual of the contour samples near the point."""
    from regtrack.tracking.uncertainty import residual_sigma

    pts = np.vstack([np.zeros((20, 2)), np.full((20, 2), 200.0)])
    d = np.r_[np.full(20, 1.0), np.full(20, 3.0)]
    res = residual_sigma([[0.0, 0.0], [200.0, 200.0], [100.0, 100.0]], Residual(pts, d),
                         scale_mm=25.0)
    assert res[0] == pytest.approx(1.0, abs=1e-6)
    assert res[1] == pytest.approx(3.0, abs=1e-6)
    assert res[2] == pytest.approx(np.sqrt(5.0), abs=1e-6)   # equidistant: RMS of 1 and 3


def test_pixel_frame_matches_the_mammogram_reader():
    """PixelFrame.from_view uses the reader's frames: a stored right-CC pixel (nipple) maps
    to the view's nipple mm, and back."""
    from regtrack.imaging.mammogram import extract_view, mammogram_from_array
    from regtrack.imaging.mammogram.synthetic import synthetic_breast

    sb = synthetic_breast(label=False, spacing=(0.25, 0.2), shape=(600, 500))
    stored = sb.image[:, ::-1]                      # right breast stored nipple-left (IHE P\L)
    nip_canon = np.array([sb.yc_mm / 0.25, sb.a_mm / 0.2 - 3])   # just inside the skin
    nip_stored = np.array([nip_canon[0], stored.shape[1] - 1 - nip_canon[1]])
    img = mammogram_from_array(stored, pixel_spacing_mm=(0.25, 0.2), view="CC", laterality="R",
                               patient_orientation=["P", "L"])
    view = extract_view(img, nipple_px=nip_stored)
    pf = PixelFrame.from_view(view)
    assert pf.shape == stored.shape
    assert np.allclose(pf.px_to_mm(nip_stored), view.nipple, atol=1e-9)
    assert np.allclose(pf.mm_to_px(view.nipple), nip_stored, atol=1e-9)
    assert np.allclose(view.nipple, [nip_canon[1] * 0.2, nip_canon[0] * 0.25], atol=1e-9)


def test_contour_gives_one_curve_per_vertex_and_their_hull(model, views):
    from shapely.geometry import Point, Polygon

    from regtrack.tracking.cc_to_mlo import track_view_contour

    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    contour = np.c_[70 + 5 * np.cos(t), 55 + 4 * np.sin(t)]
    pred = track_view_contour(model, views["CC"], views["MLO"], contour, pixels=False,
                              max_vertices=10)
    assert len(pred.segments) == 10
    hull = Polygon(pred.region_mm).buffer(1e-9)
    for s, p in zip(pred.segments, contour[::4]):
        assert np.allclose(s.source_mm, p)
        assert all(hull.covers(Point(*q)) for q in s.polyline_mm)
