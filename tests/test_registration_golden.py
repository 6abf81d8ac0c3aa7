"""Golden-section search (regtrack.registration.golden) on functions with known minima."""

from __future__ import annotations

import math

import numpy as np
import pytest

from regtrack.registration.golden import INV_PHI, golden_section


@pytest.mark.parametrize("f, a, b, xmin", [
    (lambda x: (x - 1.234) ** 2, -30.0, 30.0, 1.234),               # parabola
    (lambda x: abs(x + 7.5), -30.0, 30.0, -7.5),                     # kink (non-smooth)
    (lambda x: math.cosh(x - 3.0) + 0.1 * x, -10.0, 20.0, 3.0 - math.asinh(0.1)),
    (lambda x: -math.cos(math.radians(x - 12.0)), -30.0, 30.0, 12.0),
    (lambda x: x**4 - 3 * x**3, 0.0, 5.0, 2.25),                     # flat-ish, x^3(4x - 9) = 0
])
def test_known_minima(f, a, b, xmin):
    tol = 1e-4
    r = golden_section(f, a, b, tol=tol)
    assert r.x == pytest.approx(xmin, abs=tol)
    # evaluations: 2 initial + one per shrink by 1/phi until the bracket < tol
    expected = 2 + math.ceil(math.log(tol / (b - a)) / math.log(INV_PHI))
    assert r.evaluations == expected
    assert r.bracket[1] - r.bracket[0] < tol
    assert not r.at_edge


def test_minimum_outside_bracket_is_flagged():
    r = golden_section(lambda x: (x - 50.0) ** 2, -30.0, 30.0, tol=1e-3)
    assert r.at_edge and r.x == pytest.approx(30.0, abs=1e-3)


def test_counts_calls():
    calls = []
    r = golden_section(lambda x: calls.append(x) or np.sin(x), 3.0, 6.0, tol=1e-6)
    assert r.evaluations == len(calls)
    assert r.x == pytest.approx(1.5 * np.pi, abs=1e-6)


@pytest.mark.parametrize("a, b, tol", [(1.0, 1.0, 1e-3), (2.0, 1.0, 1e-3), (0.0, 1.0, 0.0),
                                       (0.0, float("inf"), 1e-3)])
def test_bad_bracket(a, b, tol):
    with pytest.raises(ValueError, match="golden_section"):
        golden_section(lambda x: x * x, a, b, tol=tol)
