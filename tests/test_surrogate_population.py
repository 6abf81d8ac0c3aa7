"""Known-answer tests of the population surrogate (:mod:`regtrack.surrogate.population`).

Synthetic "patients": half-ellipsoids (chest wall on the plane ``x = 0``, nipple at the
apex) filled with a regular grid of nodes and tetrahedralised by Delaunay; a few hundred
nodes each, so the whole file runs in seconds.  No simulation and no data outside the repo.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

from regtrack.model.types import AnatomicalFrame, BreastModel
from regtrack.surrogate.population import (FEATURES, PopulationSurrogate, exam_key, from_target,
                                           lopo_folds, mean_shape_baseline, node_features,
                                           nodal_error_summary, to_target)


def half_ellipsoid(a: float, b: float, c: float, *, side: str = "R", spacing: float = 7.0,
                   tumour: bool = True) -> BreastModel:
    """Breast-like model (mm): depth ``a`` along x (chest wall x = 0 -> nipple x = a),
    semi-axes ``b`` (y, superior) and ``c`` (z); grid nodes, Delaunay tets; a tumour ball of
    radius ``a / 4`` half-way to the nipple.  The origin is put at the nipple."""
    g = [np.arange(0.0, a + 1e-9, spacing), np.arange(-b, b + 1e-9, spacing),
         np.arange(-c, c + 1e-9, spacing)]
    p = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    p = p[(p[:, 0] / a) ** 2 + (p[:, 1] / b) ** 2 + (p[:, 2] / c) ** 2 <= 1.0 + 1e-9]
    p = p[np.linalg.norm(p - [a, 0, 0], axis=1) > 1e-6]
    p = np.vstack([p, [a, 0.0, 0.0]])                     # the nipple, last node
    tri = Delaunay(p)
    tets = tri.simplices
    vol = np.einsum("ij,ij->i", np.cross(p[tets[:, 1]] - p[tets[:, 0]], p[tets[:, 2]] - p[tets[:, 0]]),
                    p[tets[:, 3]] - p[tets[:, 0]])
    tets = tets[np.abs(vol) > 1e-9]
    hull = tri.convex_hull
    skin = hull[~np.all(np.abs(p[hull][..., 0]) < 1e-9, axis=1)]
    centre = np.array([a / 2, 0.0, 0.0])
    region = np.ones(len(tets), int)
    if tumour:
        region[np.linalg.norm(p[tets].mean(1) - centre, axis=1) < a / 4] = 2
    nipple = len(p) - 1
    return BreastModel(points=p - p[nipple], tets=tets, region=region,
                       tumour_id=(region == 2).astype(int), skin=skin,
                       fixed=np.abs(p[:, 0]) < 1e-9, nipple=nipple,
                       frame=AnatomicalFrame.standard(side))


def mirrored(m: BreastModel) -> BreastModel:
    """The mirror image ``z -> -z`` of ``m``, declared as the other side."""
    p = m.points * [1.0, 1.0, -1.0]
    return BreastModel(points=p, tets=m.tets[:, [0, 2, 1, 3]], region=m.region,
                       tumour_id=m.tumour_id, skin=m.skin[:, ::-1], fixed=m.fixed,
                       nipple=m.nipple, frame=AnatomicalFrame.standard("L" if m.frame.side == "R" else "R"))


def known_field(m: BreastModel, view: str) -> np.ndarray:
    """Displacement (mm, model frame) that is a smooth known function of the normalised
    features: in the plate frame, scaled by T0, t = (0.05 h d, 0.1 (l - 0.5) h, -0.3 h)
    with h = h_frac, d = depth_frac, l = lat_frac (a flattening by 30 % of T0 at the top,
    a lateral spread and an anterior push that grow with height)."""
    nf = node_features(m, view)
    h, d, lat = nf.q[:, 2], nf.q[:, 0], nf.q[:, 1]
    t = np.column_stack([0.05 * h * d, 0.1 * (lat - 0.5) * h, -0.3 * h])
    return from_target(t, nf)


TRAIN_DIMS = [(40, 50, 55, "R"), (45, 55, 60, "L"), (50, 60, 65, "R"), (55, 50, 60, "L"),
              (60, 65, 70, "R"), (48, 58, 52, "L"), (42, 62, 66, "R"), (58, 54, 62, "L")]


@pytest.fixture(scope="module")
def cohort():
    return [half_ellipsoid(a, b, c, side=s) for a, b, c, s in TRAIN_DIMS]


def test_features_invariant_to_translation():
    m = half_ellipsoid(45, 55, 60)
    moved = BreastModel(points=m.points + [12.5, -30.0, 7.0], tets=m.tets, region=m.region,
                        tumour_id=m.tumour_id, skin=m.skin, fixed=m.fixed, nipple=m.nipple,
                        frame=m.frame)
    for view in ("CC", "MLO"):
        a, b = node_features(m, view), node_features(moved, view)
        np.testing.assert_allclose(b.values, a.values, atol=1e-9)   # float round-off only
        np.testing.assert_allclose(b.q, a.q, atol=1e-12)


def test_features_consistent_under_mirroring():
    """A left breast and the mirror image of a right one have the same features, so the
    surrogate's prediction for the mirror is the mirrored prediction (z component negated)."""
    m = half_ellipsoid(45, 55, 62, side="R")
    mm = mirrored(m)
    for view in ("CC", "MLO"):
        np.testing.assert_allclose(node_features(mm, view).values, node_features(m, view).values,
                                   atol=1e-9)
    train = [half_ellipsoid(a, b, c, side=s) for a, b, c, s in TRAIN_DIMS[:3]]
    sur = PopulationSurrogate("MLO", kind="extra", per_patient=None,
                              regressor_options={"n_estimators": 5})
    sur.fit([node_features(t, "MLO") for t in train], [known_field(t, "MLO") for t in train])
    np.testing.assert_allclose(sur.predict(mm), sur.predict(m) * [1.0, 1.0, -1.0], atol=1e-9)


def test_target_round_trip():
    m = half_ellipsoid(45, 55, 60, side="L")
    nf = node_features(m, "MLO")
    u = np.random.default_rng(0).normal(size=(m.n_nodes, 3))
    np.testing.assert_allclose(from_target(to_target(u, nf), nf), u, atol=1e-12)
    assert nf.values.shape == (m.n_nodes, len(FEATURES))
    assert nf.q.min() >= -1e-12 and nf.q.max() <= 1 + 1e-12


@pytest.mark.parametrize("view", ["CC", "MLO"])
def test_ensemble_recovers_known_field(cohort, view):
    """Trained on 8 patients, predicts a 9th of new proportions (inside the training range).

    Tolerance: the field changes by at most ~0.33 T0 ~ 37 mm per unit of the normalised
    coordinates (T0 ~ 112 mm here).  Each patient's nodes sit 7 mm (~0.06 in h_frac) apart,
    but the 8 patients' grids interleave in normalised coordinates, so a test node has
    training samples within ~0.015 of it: a piecewise-constant tree fit should be within
    ~0.015 * 37 ~ 0.5 mm at a typical node.  Asserted: median below 0.5 mm and p95 below
    1.2 mm (measured 0.15 / 0.35 mm CC and 0.23 / 0.57 mm MLO with 10 trees, seed 0),
    while predicting zero is off by ~17 mm (median) on this patient."""
    test = half_ellipsoid(52, 57, 63, side="L")
    sur = PopulationSurrogate(view, kind="extra", per_patient=None,
                              regressor_options={"n_estimators": 10, "min_samples_leaf": 2})
    sur.fit([node_features(m, view) for m in cohort], [known_field(m, view) for m in cohort])
    truth = known_field(test, view)
    err = nodal_error_summary(sur.predict(test), truth)
    zero = nodal_error_summary(np.zeros_like(truth), truth)
    assert zero["median_mm"] > 10.0
    assert err["median_mm"] < 0.5, err
    assert err["p95_mm"] < 1.2, err
    assert sur.predict_s > 0 and sur.fit_s > 0
    imp = sur.importances()
    assert set(imp) == set(FEATURES) and abs(sum(imp.values()) - 1.0) < 1e-6


def test_baseline_exact_on_scaled_copies():
    """Patients that are uniform scalings (and translations) of one shape have identical
    normalised coordinates node for node; with a field that is T0 times a function of
    them, the mean-shape baseline is exact (to float round-off)."""
    base = half_ellipsoid(45, 55, 60)
    copies = []
    for k, s in enumerate((0.8, 1.0, 1.25)):
        copies.append(BreastModel(points=base.points * s + [k, 2 * k, -k], tets=base.tets,
                                  region=base.region, tumour_id=base.tumour_id, skin=base.skin,
                                  fixed=base.fixed, nipple=base.nipple, frame=base.frame))
    new = BreastModel(points=base.points * 1.1, tets=base.tets, region=base.region,
                      tumour_id=base.tumour_id, skin=base.skin, fixed=base.fixed,
                      nipple=base.nipple, frame=base.frame)
    for view in ("CC", "MLO"):
        pred = mean_shape_baseline([node_features(c, view) for c in copies],
                                   [known_field(c, view) for c in copies], node_features(new, view))
        np.testing.assert_allclose(pred, known_field(new, view), atol=1e-9)


def test_lopo_keeps_both_sides_of_an_exam_together():
    names = ["exam01", "exam02", "exam02R", "exam30L", "exam30", "exam41"]
    assert exam_key("exam02R") == exam_key("exam02") == "exam02"
    assert exam_key("exam30L") == "exam30"
    folds = lopo_folds(names)
    assert [f[0] for f in folds] == ["exam01", "exam02", "exam30", "exam41"]
    for exam, train, test in folds:
        assert sorted(train + test) == list(range(len(names)))
        assert all(exam_key(names[i]) == exam for i in test)
        assert all(exam_key(names[i]) != exam for i in train)
    assert {tuple(f[2]) for f in folds} == {(0,), (1, 2), (3, 4), (5,)}
