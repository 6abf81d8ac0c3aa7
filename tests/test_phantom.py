"""Synthetic prone breast phantom: reproducible, anatomically plausible, parametric."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from regtrack.errors import ConfigError
from regtrack.imaging.readers import read_image_volume, read_label_map
from regtrack.phantom import PhantomParams, make_phantom, phantom_params
from regtrack.phantom.geometry import mound_volume_mm3

from conftest import SAMPLE_CASES

COARSE = (1.2, 1.2, 1.6)  # variants on a coarser grid keep the tests fast


@pytest.fixture(scope="module")
def default():
    return make_phantom(PhantomParams())


def test_bundled_phantom01_is_the_default_phantom(default):
    """sample_cases/phantom01 is exactly what the generator gives (lossless DICOM, same grid)."""
    mri, labels, truth = default
    folder = SAMPLE_CASES / "phantom01"
    lab = read_label_map(folder / "mri" / "labels.nii.gz")
    np.testing.assert_array_equal(lab.data, labels.data)
    series = read_image_volume(folder / "mri" / "dicom")
    np.testing.assert_array_equal(series.data, mri.data)
    np.testing.assert_allclose(series.affine, mri.affine, atol=1e-9)
    saved = json.loads((folder / "truth" / "phantom_truth.json").read_text())
    np.testing.assert_allclose(saved["tumour_centroid_lps_mm"], truth["tumour_centroid_lps_mm"])
    np.testing.assert_allclose(saved["nipple_lps_mm"], truth["nipple_lps_mm"])


def test_reproducible_from_seed():
    p = PhantomParams(seed=5, spacing_mm=COARSE)
    m1, l1, t1 = make_phantom(p)
    m2, l2, t2 = make_phantom(p)
    np.testing.assert_array_equal(l1.data, l2.data)
    np.testing.assert_array_equal(m1.data, m2.data)
    assert t1 == t2
    _, l3, _ = make_phantom(replace(p, seed=6))
    assert not np.array_equal(l1.data, l3.data)  # another texture


@pytest.mark.parametrize("size,offset", [((25.0, 22.0, 25.0), (15.0, 30.0, 10.0)),
                                         ((12.0, 16.0, 20.0), (-20.0, 40.0, -15.0))])
def test_tumour_size_and_position(size, offset):
    """Voxel extents within 10 % of the requested diameters (surface modulation ε = 5 % plus
    one voxel of discretisation); centroid within 1.5 mm of the requested centre."""
    p = PhantomParams(tumour_size_mm=size, tumour_offset_mm=offset, spacing_mm=COARSE)
    _, labels, truth = make_phantom(p)
    np.testing.assert_allclose(truth["tumour_extent_lps_mm"], size, rtol=0.10)
    np.testing.assert_allclose(truth["tumour_centroid_lps_mm"], truth["tumour_centre_requested_lps_mm"], atol=1.5)
    assert truth["tumour_volume_mm3"] == pytest.approx(truth["tumour_volume_ellipsoid_mm3"], rel=0.15)
    # the tumour is one blob fully inside the parenchyma: no skin, muscle or air touches it
    tum = labels.data == -3
    assert ndimage.label(tum)[1] == 1
    ring = ndimage.binary_dilation(tum) & ~tum
    assert np.all(labels.data[ring] >= 1)


def test_volumes_match_the_analytic_shape(default):
    """Mound voxel volume vs π R_u R_v P Γ(1+1/q)Γ(1+2/q)/Γ(1+3/q): voxel-centre sampling
    has no bias, so 1 % covers the discretisation (measured 0.2 %) plus the ~0.3 cm^3 nipple."""
    _, _, truth = default
    assert truth["breast_mound_volume_mm3"] == pytest.approx(truth["breast_mound_volume_analytic_mm3"], rel=0.01)
    assert mound_volume_mm3(PhantomParams()) == pytest.approx(2 / 3 * np.pi * 65 * 60 * 75)
    assert truth["gland_fraction_of_mound_parenchyma"] == pytest.approx(0.3, abs=0.05)


def test_prone_anatomy(default):
    """Breast anterior (-y) of the muscle; nipple the most anterior body point; the whole
    air boundary is skin; labels follow the detailed Pelicano convention."""
    mri, labels, truth = default
    d = labels.data
    assert set(np.unique(d)) == {-3, -2, -1, 0, 1, 2, 3, 4, 5, 6, 7}
    world = lambda mask: labels.index_to_world(np.argwhere(mask))  # noqa: E731
    muscle_y = world(d == -1)[:, 1]
    tissue_y = world(d >= 1)[:, 1]
    assert tissue_y.max() < muscle_y.min()
    body = world(d != 0)
    tip = body[body[:, 1] < body[:, 1].min() + 1e-6]  # the most anterior voxel row
    nip = np.asarray(truth["nipple_lps_mm"])
    assert abs(tip[0, 1] - nip[1]) <= labels.spacing[1]
    np.testing.assert_allclose(tip.mean(0)[[0, 2]], nip[[0, 2]], atol=labels.spacing[0])
    # every body voxel touching the anterior air is skin
    air = (d == 0) & (np.arange(d.shape[1])[None, :, None] < d.shape[1] // 2)
    touching = ndimage.binary_dilation(air) & (d != 0)
    assert np.all(d[touching] == -2)
    # T1 contrast: fat brighter than gland brighter than tumour
    mean = {lab: mri.data[d == lab].mean() for lab in (-3, 2, 6)}
    assert mean[6] > mean[2] > mean[-3]
    assert 0 <= mri.data.min() and mri.data.max() <= 4095


@pytest.mark.parametrize("side", ["R", "L"])
def test_side_and_lateral_direction(side):
    """LPS x: right breast at x < 0 with lateral = -x; left breast mirrored."""
    _, _, truth = make_phantom(PhantomParams(side=side, spacing_mm=COARSE))
    nx, tx = truth["nipple_lps_mm"][0], truth["tumour_centroid_lps_mm"][0]
    if side == "R":
        assert nx < 0 and tx < nx  # tumour offset is lateral
    else:
        assert nx > 0 and tx > nx


def test_ptosis_changes_the_projection():
    _, _, short = make_phantom(PhantomParams(projection_mm=55.0, tumour_offset_mm=(10, 20, 5), spacing_mm=COARSE))
    _, _, long = make_phantom(PhantomParams(projection_mm=95.0, spacing_mm=COARSE))
    assert long["nipple_lps_mm"][1] == pytest.approx(short["nipple_lps_mm"][1] - 40.0)
    assert long["breast_mound_volume_mm3"] / short["breast_mound_volume_mm3"] == pytest.approx(95 / 55, rel=0.02)


@pytest.mark.parametrize("table,match", [
    ({"tumour_offset_mm": [60.0, 30.0, 0.0]}, "tumour_offset_mm"),
    ({"side": "X"}, "side"),
    ({"skin_thickness_mm": 0.0}, "skin_thickness_mm"),
    ({"tumor_size_mm": [20, 20, 20]}, "did you mean 'tumour_size_mm'"),
])
def test_bad_parameters_raise_config_error(table, match):
    with pytest.raises(ConfigError, match=match):
        make_phantom(phantom_params({"spacing_mm": [1.5, 1.5, 2.0], **table}))
