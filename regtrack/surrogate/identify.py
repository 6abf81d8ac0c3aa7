"""Inverse identification of tissue parameters on a surrogate (Han et al. 2012).

Han et al. identify the hyperelastic parameters by minimising the distance between
simulated and measured landmark displacements with a hybrid global search (simulated
annealing) finished by a local optimiser, a fast solver being the forward model.  Here the
forward model is a :class:`~regtrack.surrogate.model.Surrogate` (a prediction costs about
a millisecond), and the search is :func:`scipy.optimize.differential_evolution`: a
population-based global search over the box, seeded (so the same data give the same
answer on any machine), finished by its L-BFGS-B polish.  Parameters are searched in unit
coordinates, logarithmic for ``c1`` (a stiffness: its effect scales with its ratio) and
linear otherwise.

Two objectives use it:

* :func:`landmark_misfit`, Han's: the root-mean-square distance (mm) between predicted and
  observed displacements of ``M`` landmark nodes,
  :math:`J(p) = \\sqrt{\\tfrac{1}{M} \\sum_i \\lVert \\hat u_i(p) - u_i^{obs} \\rVert^2}`;
* the calibration on real mammograms (:mod:`regtrack.study.calibrate` with a surrogate),
  whose objective is the registration score.

What is reported besides the optimum (:class:`Identification`):

* **sensitivity**: central differences of the objective, ``dJ/dp`` per unit of each
  parameter, at the optimum (step 1 % of the box);
* **uncertainty**: for each parameter, the interval over which the objective stays within
  ``tolerance`` of its optimum, the others held at the optimum (a conditional profile: a
  21-point scan of the box, its ends sharpened by bisection).  ``tolerance`` is what the
  objective cannot resolve: for a landmark fit the surrogate's own error at the landmarks
  plus the measurement error.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

LOG_PARAMS = ("c1",)


def to_unit(name: str, v: float, lo: float, hi: float) -> float:
    """Parameter value -> [0, 1] over ``[lo, hi]`` (logarithmic for :data:`LOG_PARAMS`)."""
    if name in LOG_PARAMS:
        return (math.log(v) - math.log(lo)) / (math.log(hi) - math.log(lo))
    return (v - lo) / (hi - lo)


def from_unit(name: str, t: float, lo: float, hi: float) -> float:
    """Inverse of :func:`to_unit`, with ``t`` clipped to [0, 1]."""
    t = min(1.0, max(0.0, float(t)))
    if name in LOG_PARAMS:
        return math.exp(math.log(lo) + t * (math.log(hi) - math.log(lo)))
    return lo + t * (hi - lo)


@dataclass
class Identification:
    """Result of :func:`identify`.

    Attributes
    ----------
    params : dict
        The optimum (parameter name -> value, their units).
    value : float
        The objective there.
    evaluations : int
        Objective evaluations of the search.
    sensitivity : dict
        Name -> ``dJ/dp`` (objective units per parameter unit) at the optimum.
    interval : dict
        Name -> ``(low, high)``: where the objective stays within ``tolerance`` of the
        optimum, the other parameters held there.
    tolerance : float
        The objective change the interval is drawn at.
    """

    params: dict
    value: float
    evaluations: int
    sensitivity: dict = field(default_factory=dict)
    interval: dict = field(default_factory=dict)
    tolerance: float = 0.0

    def to_dict(self) -> dict:
        return {"params": self.params, "value": self.value, "evaluations": self.evaluations,
                "sensitivity": self.sensitivity,
                "interval": {k: list(v) for k, v in self.interval.items()},
                "tolerance": self.tolerance}


def _in_unit_box(objective: Callable[[dict], float], bounds: Mapping[str, tuple[float, float]]):
    """``(point, f, count)``: unit coordinates -> parameters, the objective of unit
    coordinates, and a one-item list counting its calls."""
    names = list(bounds)
    count = [0]

    def point(t) -> dict:
        return {n: from_unit(n, ti, *bounds[n]) for n, ti in zip(names, np.atleast_1d(t))}

    def f(t) -> float:
        count[0] += 1
        return float(objective(point(t)))
    return point, f, count


def identify(objective: Callable[[dict], float], bounds: Mapping[str, tuple[float, float]], *,
             tolerance: float | None, seed: int = 0, popsize: int = 15, maxiter: int = 100,
             polish: bool = True) -> Identification:
    """Minimise ``objective(params)`` over the box ``bounds`` (name -> (low, high)).

    Differential evolution (``popsize`` x dimensions members, at most ``maxiter``
    generations, seeded) then, with ``polish``, L-BFGS-B from its best member; then the
    sensitivity and the profile intervals at ``tolerance`` (see the module docstring; None
    leaves them to a later :func:`profile`, when the tolerance is known only after a check).
    """
    names = list(bounds)
    point, f, count = _in_unit_box(objective, bounds)

    res = optimize.differential_evolution(f, [(0.0, 1.0)] * len(names), seed=seed,
                                          popsize=popsize, maxiter=maxiter, tol=1e-8,
                                          polish=polish, updating="deferred")
    best = point(res.x)
    out = Identification(best, float(res.fun), count[0])
    if tolerance is not None:
        profile(objective, out, bounds, tolerance=tolerance)
    return out


def refine(objective: Callable[[dict], float], bounds: Mapping[str, tuple[float, float]],
           start: Mapping[str, float], *, step: float, xatol: float, maxfev: int = 80
           ) -> Identification:
    """Local minimisation from ``start``: bounded Nelder-Mead in the unit coordinates, an
    initial simplex of edge ``step`` and a stop at ``xatol`` (both unit coordinates)."""
    names = list(bounds)
    point, f, count = _in_unit_box(objective, bounds)
    t0 = np.array([to_unit(n, start[n], *bounds[n]) for n in names])

    simplex = [t0] + [np.clip(t0 + np.eye(len(names))[i] * step * (1 if t0[i] < 0.5 else -1),
                              0.0, 1.0) for i in range(len(names))]
    res = optimize.minimize(f, t0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * len(names),
                            options={"initial_simplex": np.array(simplex), "xatol": xatol,
                                     "fatol": 1e-6, "maxfev": maxfev})
    return Identification(point(res.x), float(res.fun), count[0])


def profile(objective: Callable[[dict], float], ident: Identification,
            bounds: Mapping[str, tuple[float, float]], *, tolerance: float,
            scan: int = 21, bisections: int = 4) -> Identification:
    """Fill ``ident``'s sensitivity (central differences, step 1 % of the box) and its
    profile intervals at ``tolerance``: a ``scan``-point scan of each parameter over the box,
    the others at the optimum, whose outermost points within the tolerance are then
    sharpened by ``bisections`` bisections against their outer neighbours (the ends to
    1/(scan - 1)/2**bisections of the box); returns ``ident``."""
    best, value = ident.params, ident.value

    def within(n: str, v: float) -> bool:
        return objective({**best, n: float(v)}) <= value + tolerance

    for n, (lo, hi) in bounds.items():
        h = 0.01 * (hi - lo)
        a, b = max(lo, best[n] - h), min(hi, best[n] + h)
        ident.sensitivity[n] = (objective({**best, n: b}) - objective({**best, n: a})) / (b - a)
        xs = np.linspace(lo, hi, scan)
        ok = np.array([within(n, v) for v in xs])
        ends = [best[n]]
        if ok.any():
            i, j = int(np.argmax(ok)), int(len(ok) - 1 - np.argmax(ok[::-1]))
            below = xs[i - 1] if i > 0 else None
            above = xs[j + 1] if j < scan - 1 else None
            ends += [_sharpen(lambda v: within(n, v), xs[i], below, bisections),
                     _sharpen(lambda v: within(n, v), xs[j], above, bisections)]
        ident.interval[n] = (min(ends), max(ends))
    ident.tolerance = float(tolerance)
    return ident


def _sharpen(inside: Callable[[float], bool], good: float, bad: float | None, steps: int) -> float:
    """The point within the tolerance nearest ``bad`` after ``steps`` bisections of
    [good, bad] (``good`` itself when it is the box's end)."""
    if bad is None:
        return float(good)
    for _ in range(steps):
        mid = 0.5 * (good + bad)
        good, bad = (mid, bad) if inside(mid) else (good, mid)
    return float(good)


def landmark_misfit(surrogate, nodes: Sequence[int], observed: np.ndarray, *,
                    fixed: Mapping[str, float] | None = None) -> Callable[[dict], float]:
    """Han's objective: RMS distance (mm) between the surrogate's displacements of the
    landmark ``nodes`` and the ``observed`` ones ``(M, 3)`` (mm).  Parameters of the
    surrogate not searched come from ``fixed``."""
    nodes = np.asarray(nodes, int)
    obs = np.asarray(observed, float).reshape(len(nodes), 3)
    fixed = dict(fixed or {})

    def J(params: dict) -> float:
        u = surrogate.predict({**fixed, **params})[nodes]
        return float(np.sqrt(np.mean(np.sum((u - obs) ** 2, axis=1))))
    return J
