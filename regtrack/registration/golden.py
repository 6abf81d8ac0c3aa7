"""Golden-section search for the minimum of a function of one variable on a bracket.

Kiefer (1953); each iteration shrinks the bracket ``[a, b]`` by the factor
:math:`1/\\varphi = (\\sqrt 5 - 1) / 2 \\approx 0.618` and costs one new evaluation, so a
bracket of width ``w`` is reduced below ``tol`` after
:math:`\\lceil \\ln(w / tol) / \\ln\\varphi \\rceil` iterations (+2 initial evaluations).
For a unimodal function the true minimiser stays inside the bracket.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class GoldenResult:
    """Outcome of :func:`golden_section`.

    ``x`` is the best point evaluated, ``fun`` its value, ``evaluations`` the number of
    function calls, ``bracket`` the final interval and ``at_edge`` whether ``x`` lies
    within ``tol`` of the initial bracket's ends (the minimum may lie outside it).
    """

    x: float
    fun: float
    evaluations: int
    bracket: tuple[float, float]
    at_edge: bool


def golden_section(f: Callable[[float], float], a: float, b: float, *, tol: float = 1e-3,
                   max_iter: int = 200) -> GoldenResult:
    """Minimise ``f`` on ``[a, b]`` by golden-section search.

    Parameters
    ----------
    f : callable
        Function of one float.
    a, b : float
        Bracket ends (``a < b``).
    tol : float
        Stop when ``b - a < tol`` (same unit as ``x``).
    max_iter : int
        Safety cap on iterations.

    Returns
    -------
    GoldenResult
    """
    if not (math.isfinite(a) and math.isfinite(b)) or b <= a:
        raise ValueError(f"golden_section: bracket [{a}, {b}] must be finite with a < b")
    if tol <= 0:
        raise ValueError(f"golden_section: tol = {tol} must be > 0")
    lo, hi = a, b
    c = hi - INV_PHI * (hi - lo)
    d = lo + INV_PHI * (hi - lo)
    fc, fd = f(c), f(d)
    n = 2
    best = (fc, c) if fc <= fd else (fd, d)
    while hi - lo > tol and n < max_iter + 2:
        if fc <= fd:
            hi, d, fd = d, c, fc
            c = hi - INV_PHI * (hi - lo)
            fc = f(c)
            best = min(best, (fc, c))
        else:
            lo, c, fc = c, d, fd
            d = lo + INV_PHI * (hi - lo)
            fd = f(d)
            best = min(best, (fd, d))
        n += 1
    fx, x = best
    return GoldenResult(x, fx, n, (lo, hi), min(x - a, b - x) < tol)
