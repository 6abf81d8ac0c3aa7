"""Breast mask, open contour, nipple, pectoral line and tumour contours: known answers on
synthetic mammograms (:mod:`regtrack.imaging.mammogram.synthetic`) whose geometry is exact.

Tolerances: the segmentation grid is 0.5 mm, so a boundary is located to about half a
working pixel (0.25 mm); over a perimeter P the area error is then about 0.25 P mm^2,
i.e. 1 % for the 60 x 50 mm half ellipse (P ~ 175 mm): we allow 2 %.  Points (nipple,
line intercepts) are allowed 1 mm (two working pixels), the pectoral search grid adds its
step (about 1.5 mm) to the intercept tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import MammogramError
from regtrack.imaging.mammogram import MammogramConfig, extract_view, mammogram_from_array
from regtrack.imaging.mammogram.contour import polygon_area
from regtrack.imaging.mammogram.synthetic import synthetic_breast

SP = (0.25, 0.25)


def _cc(**kw):
    s = synthetic_breast(**kw)
    return s, mammogram_from_array(s.image, pixel_spacing_mm=SP, view="CC", laterality="L")


def _dist_to_polyline(p, poly):
    from shapely.geometry import LineString, Point

    return LineString(poly).distance(Point(p))


def test_half_ellipse_area_nipple_and_open_contour():
    s, img = _cc()
    v = extract_view(img)
    c = v.breast_contour
    area = abs(polygon_area(c[:, ::-1]))
    assert area == pytest.approx(s.area_mm2, rel=0.02)
    assert v.meta["breast_area_mm2"] == pytest.approx(s.area_mm2, rel=0.02)
    assert np.linalg.norm(v.nipple - s.nipple_mm) < 1.0
    assert _dist_to_polyline(v.nipple, c) < 1e-9  # the nipple is a contour point
    # open: both ends on the chest wall (x ~ 0), top end first; every point on the ellipse
    assert c[0, 0] < 1.0 and c[-1, 0] < 1.0 and c[0, 1] < c[-1, 1]
    r = np.hypot(c[:, 0] / s.a_mm, (c[:, 1] - s.yc_mm) / s.b_mm)
    assert np.abs(r - 1).max() < 0.5 / s.b_mm + 0.01  # within ~0.5 mm of the true skin line
    assert v.meta["nipple"]["confidence"] > 0.5
    # mm frame: origin places the working grid in the full-resolution mm frame
    np.testing.assert_allclose(v.pixel_spacing, [0.5, 0.5])
    np.testing.assert_allclose(v.origin, [0.125, 0.125])


def test_labels_and_film_edges_are_excluded():
    s, img = _cc(label=True, film_edge_mm=1.5)
    v = extract_view(img)
    m = v.breast_mask
    r0, r1, c0, c1 = s.label_box_px
    rc = v.mm_to_pixel(np.array([[c0 * SP[1], r0 * SP[0]], [c1 * SP[1], r1 * SP[0]]]))
    (a, b), (c, d) = np.floor(rc[0]).astype(int), np.ceil(rc[1]).astype(int)
    assert not m[a:c + 1, b:d + 1].any(), "burned-in label inside the breast mask"
    assert not m[:, -4:].any() and not m[:2, :].any(), "film edge inside the breast mask"
    assert v.meta["segmentation"]["components_removed"] >= 2
    # the same breast without label and film edges gives the same contour area
    _, img2 = _cc(label=False, film_edge_mm=0.0)
    v2 = extract_view(img2)
    assert v.meta["breast_area_mm2"] == pytest.approx(v2.meta["breast_area_mm2"], rel=0.005)


def test_film_edge_band_along_chest_wall_is_cut():
    s = synthetic_breast(label=False, film_edge_mm=0.0)
    img = s.image.copy()
    x = np.arange(img.shape[1]) * SP[1]
    glow = 0.2 * np.clip(1 - x / 8.0, 0, None)  # 8 mm glow along the chest-wall edge
    img = np.maximum(img, glow[None, :])
    v = extract_view(mammogram_from_array(img, pixel_spacing_mm=SP, view="CC", laterality="L"))
    bands = v.meta["segmentation"]["film_edge_bands"]
    assert bands and all(b["edge"] == "left" for b in bands)
    assert v.meta["breast_area_mm2"] == pytest.approx(s.area_mm2, rel=0.03)
    c = v.breast_contour
    assert c[:, 1].min() > s.yc_mm - s.b_mm - 2 and c[:, 1].max() < s.yc_mm + s.b_mm + 2


def test_pectoral_line_and_mlo_nipple():
    s = synthetic_breast(shape=(720, 400), yc_mm=60, b_mm=90, a_mm=70, pectoral_mm=(30, 80))
    img = mammogram_from_array(s.image, pixel_spacing_mm=SP, view="MLO", laterality="L")
    v = extract_view(img)
    (xa, ya), (xb, yb) = v.meta["pectoral"]["line_mm"]
    assert ya < 0.5 and xb < 0.5
    assert xa == pytest.approx(30, abs=2.5) and yb == pytest.approx(80, abs=2.5)
    # the muscle is not breast: no mask pixel well inside the triangle
    xy = v.pixel_to_mm(np.argwhere(v.breast_mask))
    assert np.all(xy[:, 0] / 30 + xy[:, 1] / 80 > 0.95)
    # nipple: farthest skin point from the pectoral line (analytic for the ellipse:
    # the point whose outward normal is parallel to the line normal)
    n = np.array([1 / 30, 1 / 80])
    t = np.arctan2(n[1] * s.b_mm, n[0] * s.a_mm)
    expect = np.array([s.a_mm * np.cos(t), s.yc_mm + s.b_mm * np.sin(t)])
    assert np.linalg.norm(v.nipple - expect) < 3.0  # flat apex along the line: see docstring
    assert v.meta["nipple"]["method"].endswith("pectoral line")
    # the skin line starts at the top edge, right of the muscle, and ends on the chest wall
    c = v.breast_contour
    assert c[0, 1] < 1.0 and c[0, 0] > 30 and c[-1, 0] < 1.0


def test_pectoral_removal_can_be_switched_off():
    s = synthetic_breast(shape=(720, 400), yc_mm=60, b_mm=90, a_mm=70, pectoral_mm=(30, 80))
    img = mammogram_from_array(s.image, pixel_spacing_mm=SP, view="MLO", laterality="L")
    v = extract_view(img, config=MammogramConfig(remove_pectoral=False))
    assert v.meta["pectoral"] is None and v.meta["chest_wall"] == "image edge x = 0"


def test_given_nipple_is_mapped_from_the_dicom_grid():
    s = synthetic_breast()
    stored = s.image[:, ::-1]  # right breast, IHE hanging
    img = mammogram_from_array(stored, pixel_spacing_mm=SP, view="CC", laterality="R")
    w = stored.shape[1]
    nip_rc = [s.yc_mm / SP[0], (w - 1) - s.a_mm / SP[1]]
    v = extract_view(img, nipple_px=nip_rc)
    np.testing.assert_allclose(v.nipple, s.nipple_mm, atol=1e-9)
    assert v.meta["nipple"]["method"] == "given (nipple_px)"
    assert v.meta["nipple"]["distance_to_contour_mm"] < 0.5
    with pytest.raises(MammogramError, match=r"nipple_px \[5000, 3\] lies outside the image"):
        extract_view(img, nipple_px=[5000, 3])


def test_tumour_polygon_and_mask_in_dicom_grid():
    import cv2

    s = synthetic_breast()
    stored = s.image[:, ::-1]
    h, w = stored.shape
    img = mammogram_from_array(stored, pixel_spacing_mm=SP, view="CC", laterality="R")
    poly_rc = np.array([[260.0, 200.0], [300.0, 200.0], [300.0, 260.0], [260.0, 260.0]])
    v = extract_view(img, tumour_polygon_px=poly_rc)
    t = v.tumour_contours[0]
    expect = np.column_stack([((w - 1) - poly_rc[:, 1]) * SP[1], poly_rc[:, 0] * SP[0]])
    np.testing.assert_allclose(t, expect)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [poly_rc[:, ::-1].astype(np.int32)], 1)
    vm = extract_view(img, tumour_mask=mask.astype(bool))
    tm = vm.tumour_contours[0]
    # pixel-centre polygon 40 x 60 px vs a 41 x 61 px mask traced at its pixel edges
    assert abs(polygon_area(tm)) == pytest.approx(41 * 61 * SP[0] * SP[1], rel=0.01)
    np.testing.assert_allclose(tm.mean(0), t.mean(0), atol=0.2)
    with pytest.raises(MammogramError, match="tumour mask shape"):
        extract_view(img, tumour_mask=np.ones((5, 5), bool))


def test_tumour_from_seed_recovers_a_blurred_disk():
    s = synthetic_breast(tumour_mm=(35.0, 70.0, 6.0), label=False)
    img = mammogram_from_array(s.image, pixel_spacing_mm=SP, view="CC", laterality="L")
    seed = [70.0 / SP[0] + 6, 35.0 / SP[1] - 4]  # off-centre seed, still inside
    v = extract_view(img, tumour_seed_px=seed)
    t = v.tumour_contours[0]
    r_eq = np.sqrt(abs(polygon_area(t)) / np.pi)
    assert r_eq == pytest.approx(6.0, abs=0.3)
    np.testing.assert_allclose(t.mean(0), [35.0, 70.0], atol=0.3)
    with pytest.raises(MammogramError, match=r"tumour seed \[10.0, 390.0\]: (the seed is not "
                       "brighter|no closed outline found).*polygon"):
        extract_view(img, tumour_seed_px=[10, 390])  # background


def test_blank_image_is_a_clear_error():
    with pytest.raises(MammogramError, match=r"^blank: no breast found"):
        mammogram_from_array(np.r_[np.zeros((99, 100)), np.ones((1, 100))],
                             pixel_spacing_mm=SP, source="blank")
