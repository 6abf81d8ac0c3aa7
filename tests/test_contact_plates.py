"""Rigid plate geometry (regtrack.mechanics.plates) against hand-computed geometry."""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import ConfigError
from regtrack.mechanics.plates import RigidPlate


def _plate(**kw):
    base = dict(name="p", origin=(0.0, 0.0, 0.0), normal=(0, 0, 1), e1=(1, 0, 0),
                s_range=(0.0, np.inf), edge_radius=5.0)
    base.update(kw)
    return RigidPlate(**base)


def test_gap_normal_hand_values():
    """Face, below-face, side and rounded-edge points; values worked out by hand (r = 5)."""
    pl = _plate()
    x = np.array([
        [10.0, 3.0, 2.0],   # above the face: gap = h = 2, n = +z
        [10.0, 3.0, -1.0],  # 1 mm under the face: gap = -1, n = +z
        [-3.0, 0.0, -5.0],  # beside the edge at the axis height: gap = 3 - 5 = -2, n = -x
        [-3.0, 0.0, -1.0],  # on the rounded edge: |(-3, 0, 4)| = 5 -> gap 0
        [-6.0, 0.0, -1.0],  # outside the edge: |(-6, 0, 4)| - 5
        [10.0, 0.0, -30.0],  # deep below the face inside the footprint: half-space
    ])
    q = pl.query(x)
    np.testing.assert_allclose(q.gap, [2, -1, -2, 0, np.sqrt(52) - 5, -30], atol=1e-12)
    np.testing.assert_allclose(q.normal[0], [0, 0, 1])
    np.testing.assert_allclose(q.normal[2], [-1, 0, 0])
    np.testing.assert_allclose(q.normal[3], [-0.6, 0, 0.8], atol=1e-12)
    np.testing.assert_allclose(q.normal[5], [0, 0, 1])
    # the closest point is on the surface and x = closest + gap * n
    np.testing.assert_allclose(pl.query(q.closest).gap, 0.0, atol=1e-10)
    np.testing.assert_allclose(q.closest + q.gap[:, None] * q.normal, x, atol=1e-12)


def test_corner_is_spherical_and_finite_limits():
    pl = _plate(s_range=(-10.0, 10.0), t_range=(-20.0, 20.0), edge_radius=2.0)
    # beyond the (+s, +t) corner: distance to the corner axis point (10, 20, -2)
    x = np.array([[13.0, 24.0, -2.0 + 0.0]])
    q = pl.query(x)
    np.testing.assert_allclose(q.gap, [5.0 - 2.0])
    np.testing.assert_allclose(q.normal, [[0.6, 0.8, 0.0]])


def test_oblique_plate_and_translation():
    """A 45-degree plate: gap is the height along its normal; moving it shifts the gap."""
    n = np.array([0.0, 1.0, -1.0]) / np.sqrt(2)
    pl = RigidPlate(name="mlo", origin=(0, 0, 0), normal=n, e1=(1, 0, 0), edge_radius=3.0)
    x = np.array([[5.0, 2.0, -2.0]])
    assert pl.query(x).gap[0] == pytest.approx(4.0 / np.sqrt(2))
    moved = pl.translated(n * 1.5)
    assert moved.query(x).gap[0] == pytest.approx(4.0 / np.sqrt(2) - 1.5)
    np.testing.assert_allclose(moved.to_model(moved.to_local(x)), x)


@pytest.mark.parametrize("seed", [0, 1])
def test_normal_derivative_by_finite_differences(seed):
    rng = np.random.default_rng(seed)
    pl = _plate(s_range=(-5.0, 40.0), t_range=(-30.0, 30.0), edge_radius=4.0)
    # points around the rounded edges, corners and face
    x = np.column_stack([rng.uniform(-12, 50, 200), rng.uniform(-40, 40, 200),
                         rng.uniform(-12, 6, 200)])
    _check_derivatives(pl, x, h=1e-6, atol_dn=1e-5)


def _check_derivatives(pl, x, *, h, atol_dn):
    """dn/dx of the query against central differences of the normal, and dg/dx = n."""
    q = pl.query(x, curvature=True)
    for k in range(3):
        dx = np.zeros(3)
        dx[k] = h
        fd = (pl.query(x + dx).normal - pl.query(x - dx).normal) / (2 * h)
        np.testing.assert_allclose(q.dn_dx[:, :, k], fd, atol=atol_dn)
        fg = (pl.query(x + dx).gap - pl.query(x - dx).gap) / (2 * h)
        np.testing.assert_allclose(fg, q.normal[:, k], atol=1e-6)  # dg/dx = n


@pytest.mark.parametrize("kw, match", [
    (dict(normal=(0, 0, 0)), "normal"),
    (dict(e1=(0, 0, 2)), "e1"),
    (dict(s_range=(3.0, 1.0)), "s_range"),
    (dict(edge_radius=0.0), "edge_radius"),
])
def test_bad_plate_raises_config_error(kw, match):
    with pytest.raises(ConfigError, match=match):
        _plate(**kw)


def test_opening_gap_normal_hand_values():
    """A plate with a 40 x 30 mm opening (s 10..50, t -15..15), edge radius 5: points over
    the opening see its rounded rim, points beside it the flat face (values by hand)."""
    pl = _plate(window=(10.0, 50.0, -15.0, 15.0))
    x = np.array([
        [30.0, 0.0, 2.0],    # over the centre, above the face: nearest side t = +-15
        [30.0, 0.0, -3.0],   # bulging 3 mm into the opening, 15 mm from the side
        [12.0, 0.0, -1.0],   # 2 mm inside the rim at s = 10, 1 mm deep: |(2, 4)| - 5
        [12.0, 0.0, -8.0],   # deeper than r: 2 mm from the side's axis line, gap 2 - 5
        [30.0, 13.0, 0.0],   # nearest side t = 15: |(-2, 5)| - 5
        [5.0, 0.0, 1.0],     # beside the opening over the face: gap = h
        [30.0, 20.0, -0.5],  # beside the opening (t > 15), under the face: half-space
    ])
    q = pl.query(x, curvature=True)
    np.testing.assert_allclose(q.gap, [np.sqrt(15**2 + 7**2) - 5, np.sqrt(15**2 + 2**2) - 5,
                                       np.sqrt(20) - 5, 2 - 5, np.sqrt(29) - 5, 1, -0.5],
                               atol=1e-12)
    np.testing.assert_allclose(q.normal[2], np.array([2.0, 0, 4]) / np.sqrt(20), atol=1e-12)
    np.testing.assert_allclose(q.normal[3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(q.normal[4], np.array([0, -2.0, 5]) / np.sqrt(29), atol=1e-12)
    np.testing.assert_allclose(q.normal[5:], [[0, 0, 1]] * 2, atol=1e-12)
    np.testing.assert_allclose(pl.query(q.closest).gap, 0.0, atol=1e-10)
    np.testing.assert_allclose(q.closest + q.gap[:, None] * q.normal, x, atol=1e-12)
    # the gap is continuous across the opening's outline on the face (both sides -> 0)
    for s in (10.0 - 1e-9, 10.0 + 1e-9):
        assert abs(pl.query(np.array([[s, 0.0, 0.0]])).gap[0]) < 1e-6


@pytest.mark.parametrize("seed", [0, 1])
def test_opening_normal_derivative_by_finite_differences(seed):
    """dn/dx and dg/dx = n over an opening's rim (away from its diagonals, where the
    nearest side changes and the normal turns)."""
    rng = np.random.default_rng(seed)
    pl = _plate(s_range=(-5.0, 80.0), t_range=(-60.0, 60.0), edge_radius=4.0,
                window=(10.0, 50.0, -15.0, 15.0))
    x = np.column_stack([rng.uniform(0, 60, 400), rng.uniform(-25, 25, 400),
                         rng.uniform(-8, 4, 400)])
    y = pl.to_local(x)
    d = np.column_stack([y[:, 0] - 10, 50 - y[:, 0], y[:, 1] + 15, 15 - y[:, 1]])
    srt = np.sort(d, axis=1)
    x = x[(srt[:, 1] - srt[:, 0] > 1e-3) & (np.abs(d).min(axis=1) > 1e-3)]  # off diagonals and sides
    assert (pl._window_side(pl.to_local(x)) >= 0).sum() > 100
    _check_derivatives(pl, x, h=1e-7, atol_dn=1e-4)


def test_opening_outside_the_face_raises_config_error():
    with pytest.raises(ConfigError, match="window"):
        _plate(window=(-2.0, 20.0, -5.0, 5.0))  # crosses the chest-wall edge s = 0
