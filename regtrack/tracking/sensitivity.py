r"""1-sigma uncertainty of points tracked in 3-D, from the tissue's c1, nu and the plate
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

With a per-patient surrogate of the view (``--surrogate DIR``, :mod:`regtrack.surrogate`)
the three compressions are not simulated: each ``Delta x_p`` comes from the surrogate's
difference :math:`\hat u(p + \delta_p) - \hat u(p)` added to the full simulation's
deformed nodes, so the mapped positions stay the full model's and only their sensitivity
is predicted (a difference of two predictions, in which most of the surrogate's own error
cancels).  ``p`` is the case's setting: its homogeneous tissue c1 (for
``tissue_model = "composition"`` the one c1 all tissue gets), ``nu`` and the simulated D.
Each term records where it came from.
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
    sources: dict[str, str] | None = None


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
                simulate: bool = True, progress: Callable[[str], None] | None = None,
                surrogate: Any = None) -> PointSigma:
    """1-sigma uncertainty (mm) of the mapped positions of ``lps_mm`` (see the module);
    with ``surrogate`` (of ``state.view``) the perturbed compressions are predicted."""
    from regtrack.case import load_case, resolve_configs
    from regtrack.tracking.compressed import open_compressed
    from regtrack.tracking.deformation import DeformationMap

    configs = resolve_configs(load_case(case_dir, deep=False))
    base = map_points(state.dmap, names, lps_mm, inverse=inverse).mapped_lps_mm
    terms: dict[str, np.ndarray] = {}
    sources: dict[str, str] = {}
    ovs = perturbations(configs, state.view, state.summary.get("D"))
    p0 = None if surrogate is None else surrogate_point(configs, state, surrogate)
    for key, ov in ovs.items():
        if p0 is not None:
            p1 = {**p0, **_perturbed(key, ov, p0, configs, state.view)}
            du = surrogate.predict(p1) - surrogate.predict(p0)
            other = DeformationMap(state.dmap.reference, state.dmap.deformed + du,
                                   state.dmap.tets, state.dmap.frame, state.view)
            sources[key] = "surrogate"
        else:
            if progress is not None:
                progress(f"uncertainty: the {state.view} compression with {key} at +1 sigma")
            other = open_compressed(case_dir, state.view, cache_dir=cache_dir, overrides=ov,
                                    simulate=simulate, progress=progress).dmap
            sources[key] = "simulation"
        moved = map_points(other, names, lps_mm, inverse=inverse).mapped_lps_mm
        terms[key] = np.linalg.norm(moved - base, axis=1)
    total = np.sqrt(sum((t ** 2 for t in terms.values()), np.zeros(len(base))))
    return PointSigma(total, terms, ovs, sources)


def _perturbed(key: str, ov: dict, p0: dict, configs: Any, view: str) -> dict:
    """The surrogate parameter a :func:`perturbations` entry moves, at its moved value
    (c1 by the same factor as the tissue's)."""
    if key == "c1":
        return {"c1": p0["c1"] * (1.0 + configs.tracking.c1_rel_sigma)}
    if key == "nu":
        return {"nu": ov["mechanics"]["nu"]}
    return {"target_D": ov["protocol"][view]["target_D"]}


def surrogate_point(configs: Any, state: CompressedState, surrogate: Any) -> dict:
    """The case's setting as the surrogate's parameters: c1 (kPa, the one c1 of the
    homogeneous or composition tissue), nu and the simulated D.

    Raises
    ------
    ConfigError
        The surrogate is of another view or mesh, lacks c1, nu or target_D, or the case's
        tissue is heterogeneous (no one c1 to move).
    """
    from regtrack.errors import ConfigError
    from regtrack.mechanics.materials import tissue_stiffness

    mech, model = configs.mechanics, state.model
    view = str((surrogate.meta.get("validation") or {}).get("view", "")).upper()
    problems = []
    if view != state.view:
        problems.append(f"the surrogate is of view {view or '?'}, not {state.view}")
    if surrogate.n_nodes != model.n_nodes:
        problems.append(f"the surrogate's mesh has {surrogate.n_nodes} nodes, the case's "
                        f"{model.n_nodes}")
    if set(surrogate.names) != {"c1", "nu", "target_D"}:
        problems.append(f"the surrogate takes {', '.join(surrogate.names)}; the uncertainty "
                        "needs exactly c1, nu and target_D")
    if mech.tissue_model == "heterogeneous":
        problems.append("tissue_model = 'heterogeneous' has no one tissue c1 to move")
    if problems:
        raise ConfigError("--surrogate: " + "; ".join(problems) + "; rebuild it with "
                          f"`regtrack surrogate build CASE --view {state.view.lower()}`")
    c1 = mech.tissue_c1_kpa
    if mech.tissue_model == "composition":
        c1 = tissue_stiffness(model.region, model.tissue_label, np.abs(model.tet_volumes()),
                              mech).mean_kpa
    return {"c1": float(c1), "nu": float(mech.nu), "target_D": float(state.summary["D"])}
