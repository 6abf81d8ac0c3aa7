"""Space-filling designs over the surrogate's parameter box.

A Latin hypercube (McKay et al. 1979; :class:`scipy.stats.qmc.LatinHypercube`, optimised by
random coordinate swaps to a lower centred discrepancy) places ``n`` points so that each
parameter's range is cut into ``n`` equal strata with exactly one point in each.  The
parameters use the study names (:mod:`regtrack.study.params`): ``c1`` (kPa), ``nu``,
``target_D`` (fraction of the breast thickness), ``friction``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Parameters a surrogate may vary, with their unit (study names).
UNITS = {"c1": "kPa", "nu": "-", "target_D": "-", "friction": "-"}


@dataclass(frozen=True)
class ParameterBox:
    """Names and ranges of the varied parameters (units: :data:`UNITS`)."""

    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]

    def __post_init__(self) -> None:
        for n, lo, hi in zip(self.names, self.lower, self.upper):
            if n not in UNITS:
                raise ValueError(f"parameter '{n}': use one of {', '.join(UNITS)}")
            if not hi > lo:
                raise ValueError(f"parameter {n}: range [{lo}, {hi}] must have upper > lower")

    def sample(self, n: int, *, seed: int) -> np.ndarray:
        """``n`` Latin-hypercube points ``(n, d)`` in the box (reproducible by ``seed``)."""
        from scipy.stats import qmc

        if n < 1:
            raise ValueError(f"n = {n}: need at least one point")
        try:
            lhs = qmc.LatinHypercube(d=len(self.names), optimization="random-cd", rng=seed)
        except TypeError:  # scipy < 1.15 names the generator ``seed``
            lhs = qmc.LatinHypercube(d=len(self.names), optimization="random-cd", seed=seed)
        unit = lhs.random(n)
        return qmc.scale(unit, self.lower, self.upper)


def default_box(c1_kpa: float) -> ParameterBox:
    """c1 in [0.5, 2] x ``c1_kpa``, nu in [0.45, 0.49], D in [0.25, 0.45]."""
    return ParameterBox(("c1", "nu", "target_D"), (0.5 * c1_kpa, 0.45, 0.25),
                        (2.0 * c1_kpa, 0.49, 0.45))
