"""Plate frames (regtrack.virtual.frames): orientation conventions of the CC/MLO plates."""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import ConfigError
from regtrack.virtual.frames import plate_frame


@pytest.mark.parametrize("side", ["L", "R"])
@pytest.mark.parametrize("view", ["CC", "MLO"])
def test_frame_is_orthonormal(view, side):
    f = plate_frame(view, side)
    R = f.rotation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # (e_x, e_down, n) right-handed for a right breast, mirrored for a left breast
    assert np.linalg.det(R) == pytest.approx(1.0 if side == "R" else -1.0)


def test_cc_right_breast_axes():
    f = plate_frame("cc", "R")
    np.testing.assert_allclose(f.normal, [0, 1, 0])          # lower -> upper plate: superior
    np.testing.assert_allclose(f.e_down, [0, 0, -1])         # medial of a right breast = -z
    assert f.angle_deg == 0.0
    # a point 10 mm anterior and 5 mm medial of the nipple: X = 10, Y = +5 (down = medial)
    np.testing.assert_allclose(f.to_plane([10.0, 3.0, -5.0]), [10.0, 5.0])
    assert f.height([10.0, 3.0, -5.0]) == pytest.approx(3.0)


def test_mlo_left_breast_is_45_deg_superomedial():
    f = plate_frame("MLO", "L")
    s = np.sqrt(0.5)
    np.testing.assert_allclose(f.normal, [0, s, s])          # towards superior + medial (+z)
    np.testing.assert_allclose(f.e_down, [0, -s, s])         # infero-medial
    assert f.angle_deg == 45.0


def test_local_roundtrip_and_origin():
    f = plate_frame("MLO", "R", angle_deg=50.0, origin=(1.0, -2.0, 3.0))
    p = np.random.default_rng(0).normal(size=(20, 3)) * 30
    np.testing.assert_allclose(f.to_model(f.to_local(p)), p, atol=1e-12)
    np.testing.assert_allclose(f.to_local(f.origin), 0.0, atol=1e-12)


@pytest.mark.parametrize("view, side, match", [("ML", "R", "view 'ML'"), ("CC", "X", "side 'X'")])
def test_bad_view_or_side(view, side, match):
    with pytest.raises(ConfigError, match=match):
        plate_frame(view, side)
