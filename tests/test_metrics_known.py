"""Metrics (regtrack.metrics) on configurations with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from regtrack import _io
from regtrack.metrics import (
    compression_degree,
    compute_metrics,
    dice,
    distance_stats,
    similarity_percent,
)
from regtrack.registration import align
from regtrack.registration.align import Objective
from regtrack.registration.geometry import ClosestPoints, polygon, rotate_about
from regtrack.views import MammogramView


def test_similarity_percent_half_correction():
    # real contour: the x axis; virtual: the same line turned by +10 deg about the nipple (0, 0).
    # v(theta) = R(theta) v: at theta = 0 each distance is |x| sin 10, at theta = -5 |x| sin 5.
    x = np.linspace(-50, 50, 201)
    real = np.stack([np.linspace(-80, 80, 321), np.zeros(321)], 1)
    virt = rotate_about(np.stack([x, np.zeros_like(x)], 1), np.zeros(2), 10.0)
    obj = Objective(virt, ClosestPoints(real, closed=False), np.zeros(2))
    expected = (1 - math.sin(math.radians(5)) / math.sin(math.radians(10))) * 100  # 49.24 %
    assert similarity_percent(obj, -5.0) == pytest.approx(expected, rel=1e-9)
    assert similarity_percent(obj, -10.0) == pytest.approx(100.0, abs=1e-9)
    assert similarity_percent(obj, 0.0) == 0.0
    assert obj(0.0) == pytest.approx(np.sum((x * math.sin(math.radians(10))) ** 2))


def test_compression_degree():
    assert compression_degree(60.0, 45.0) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="thickness_before_mm"):
        compression_degree(0.0, 1.0)


def test_dice_of_half_overlapping_squares():
    a = polygon(np.array([[0, 0], [10, 0], [10, 10], [0, 10.0]]))
    b = polygon(np.array([[5, 0], [15, 0], [15, 10], [5, 10.0]]))
    assert dice(a, b) == pytest.approx(0.5)
    assert dice(a, a) == pytest.approx(1.0)


def test_distance_stats_parallel_lines():
    a = np.stack([np.linspace(0, 100, 11), np.full(11, 2.0)], 1)
    b = np.stack([np.linspace(0, 100, 7), np.zeros(7)], 1)
    s = distance_stats(a, b, closed=False, spacing=0.5)
    assert (s.mean, s.p95, s.max, s.hausdorff) == pytest.approx((2.0, 2.0, 2.0, 2.0))
    c = np.vstack([a, [[103.0, 2.0]]])  # 3 mm overhang: Hausdorff = hypot(3, 2)
    assert distance_stats(c, b, closed=False, spacing=0.5).hausdorff == pytest.approx(math.hypot(3, 2))


def _circle(c, r, n=720):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], 1)


def test_centroid_distances_and_dice_for_radial_shifts():
    # symmetric breast (half-ellipse, nipple at its apex on the x axis) and a tumour on the axis:
    # radial offsets cannot be undone by a rotation about the nipple, so theta_p = 0 by
    # symmetry and the centroid distances equal the offsets.
    t = np.linspace(-np.pi / 2, np.pi / 2, 721)
    breast = np.stack([80 * np.cos(t), 60 * np.sin(t)], 1)
    nipple = np.array([80.0, 0.0])
    real = MammogramView("CC", "R", breast, nipple, [_circle((40.0, 0.0), 5.0)])
    virt = MammogramView("CC", "R", breast + [4.0, 0.0], nipple,
                         [_circle((45.0, 0.0), 5.0)])
    al = align(real, virt)
    assert al.theta_p == pytest.approx(0.0, abs=0.01)
    m = compute_metrics(al, real, virt, D=0.4)
    assert m.d_B == pytest.approx(4.0, abs=1e-3)
    assert m.d_T == pytest.approx(5.0, abs=1e-3)
    # two radius-5 discs 5 mm apart: lens area 2 r^2 acos(d/2r) - (d/2) sqrt(4r^2 - d^2)
    lens = 2 * 25 * math.acos(0.5) - 2.5 * math.sqrt(75)
    assert m.dice_tumour == pytest.approx(lens / (math.pi * 25), abs=2e-3)
    assert m.D == 0.4
    d = m.to_dict()
    assert '"d_T"' in _io.to_json(d) and d["tumour_distance"]["n_points"] > 0


def test_metrics_refuse_other_view():
    from regtrack.errors import RegistrationError

    t = np.linspace(-np.pi / 2, np.pi / 2, 181)
    breast = np.stack([80 * np.cos(t), 60 * np.sin(t) + 5 * np.cos(t) ** 2 * np.sin(2 * t)], 1)
    real = MammogramView("CC", "R", breast, np.array([80.0, 0.0]), [_circle((40.0, 10.0), 5.0)])
    virt = MammogramView("CC", "R", rotate_about(breast, np.array([80.0, 0.0]), 3.0),
                         np.array([80.0, 0.0]), [rotate_about(_circle((40.0, 10.0), 5.0),
                                                              np.array([80.0, 0.0]), 3.0)])
    al = align(real, virt)
    m = compute_metrics(al, real, virt)
    # virtual = real turned by +3 deg about the nipple: every similarity is ~100 %
    assert min(m.bs_av, m.bs_av_b, m.ts_av, m.ts_av_t) > 99.0
    assert al.theta_p == pytest.approx(-3.0, abs=0.1)
    virt.view = "MLO"
    with pytest.raises(RegistrationError, match="cannot be scored"):
        compute_metrics(al, real, virt)
