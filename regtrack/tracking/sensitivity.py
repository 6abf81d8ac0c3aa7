"""1-sigma uncertainty of points tracked in 3-D, from the tissue's c1, nu and the plate
position, by simulating again (``regtrack track --view V --uncertainty``).

Each parameter ``p`` is moved by its 1-sigma value (``[tracking]`` of case.toml:
``c1_rel_sigma``, ``nu_sigma``, ``degree_sigma``), the compression is simulated again
(through the stage cache, so a repeated call costs nothing) and every point is mapped
through it.  With ``Delta x_p`` the change of a point's mapped position, the linearised
propagation of independent errors gives

.. math::

    \\sigma = \\sqrt{\\sum_p \\lVert \\Delta x_p \\rVert^2}  \\quad (\\text{mm}).

One-sided differences: ``c1 (1 + c1_rel_sigma)`` (for a composition model, fat and gland
both), ``nu - nu_sigma`` (nu stays below 0.5), ``D + degree_sigma`` (the plate moved
further by ``degree_sigma T_0``).  Under a prescribed plate travel a homogeneous breast's
shape does not depend on c1 where no gravity acts (the biopsy compression): its c1 term
is then about zero, as it should be.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from regtrack.tracking.compressed import CompressedState, map_points


@dataclass(frozen=True)
class PointSigma:
    """Per point: ``sigma_mm`` (M,), and each parameter's ``|Delta x|`` (mm)."""

    sigma_mm: np.ndarray
    terms_mm: dict[str, np.ndarray]
    overrides: dict[str, dict]


def perturbations(configs: Any, view: str, D: float | None) -> dict[str, dict]:
    """The 1-sigma overrides (case.toml layout) of each parameter (module docstring)."""
    mech, cfg = configs.mechanics, configs.tracking
    out: dict[str, dict] = {}
    f = 1.0 + cfg.c1_rel_sigma
    if cfg.c1_rel_sigma > 0:
        if mech.tissue_model == "homogeneous":
            out["c1"] = {"mechanics": {"tissue_c1_kpa": mech.tissue_c1_kpa * f}}
        else:
            keys = [k for k in ("fat_c1_kpa", "gland_c1_kpa") if getattr(mech, k) is not None]
            out["c1"] = {"mechanics": {k: getattr(mech, k) * f for k in keys}}
    if cfg.nu_sigma > 0:
        out["nu"] = {"mechanics": {"nu": max(mech.nu - cfg.nu_sigma, 0.0)}}
    if cfg.degree_sigma > 0 and D is not None:
        out["plate"] = {"protocol": {view: {"target_D": min(D + cfg.degree_sigma, 0.9)}}}
    return out


def point_sigma(case_dir: str | Path, state: CompressedState, names, lps_mm, *,
                inverse: bool = False, cache_dir: str | Path | None = None,
                simulate: bool = True, progress: Callable[[str], None] | None = None
                ) -> PointSigma:
    """1-sigma uncertainty (mm) of the mapped positions of ``lps_mm`` (see the module)."""
    from regtrack.case import load_case, resolve_configs
    from regtrack.tracking.compressed import open_compressed

    configs = resolve_configs(load_case(case_dir, deep=False))
    base = map_points(state.dmap, names, lps_mm, inverse=inverse).mapped_lps_mm
    terms: dict[str, np.ndarray] = {}
    ovs = perturbations(configs, state.view, state.summary.get("D"))
    for key, ov in ovs.items():
        if progress is not None:
            progress(f"uncertainty: the {state.view} compression with {key} at +1 sigma")
        other = open_compressed(case_dir, state.view, cache_dir=cache_dir, overrides=ov,
                                simulate=simulate, progress=progress)
        moved = map_points(other.dmap, names, lps_mm, inverse=inverse).mapped_lps_mm
        terms[key] = np.linalg.norm(moved - base, axis=1)
    total = np.sqrt(sum((t ** 2 for t in terms.values()), np.zeros(len(base))))
    return PointSigma(total, terms, ovs)
