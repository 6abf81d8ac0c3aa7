"""The pipeline's metrics with the compression predicted by surrogates instead of simulated.

:class:`SurrogatePipeline` holds a case's model, real mammograms and per-view surrogates;
:meth:`SurrogatePipeline.rows` predicts each view's displacement at a parameter point
(about a millisecond), and from there runs the pipeline's own stages: the virtual
mammogram (:func:`regtrack.pipeline.stages.virtual_stage`, outlines only: the X-ray-like
image is not rendered) and the registration with the paper's metrics
(:func:`regtrack.pipeline.stages.align_stage`).  The rows have the layout
of ``regtrack run``'s (``BS_Av``, ``TS_Av``, ``theta_p``, ``D``, ...), with ``surrogate``
set to True and no force (a surrogate predicts shape only).

The model is the mesh the surrogate was trained on (the stage cache's, found from the
same case and ``[model]`` settings); a surrogate of a different node count is refused.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from regtrack.errors import ConfigError


class SurrogatePipeline:
    """A case's views evaluated with surrogates (see the module docstring).

    Parameters
    ----------
    case : regtrack.case.Case
        The loaded case (with its mammograms).
    surrogates : dict
        View (``"CC"``/``"MLO"``) -> :class:`~regtrack.surrogate.model.Surrogate`.
    cache_dir : path
        The stage cache holding (or receiving) the case's mesh.
    overrides : dict, optional
        Override sections, as for ``regtrack run`` (the calibration's fixed values).
    """

    def __init__(self, case: Any, surrogates: dict, *, cache_dir: str | Path,
                 overrides: dict | None = None):
        from regtrack.case import resolve_configs
        from regtrack.pipeline import stages
        from regtrack.pipeline.geometry import apply_geometry
        from regtrack.pipeline.run import open_run

        self.views = tuple(v.upper() for v in surrogates)
        missing = [v for v in self.views if v not in case.views]
        if missing:
            raise ConfigError(f"{case.toml_path}: a surrogate of {', '.join(missing)} is given "
                              "but the case has no mammogram of that view")
        self.surrogates = {v.upper(): s for v, s in surrogates.items()}
        # the metrics need the outlines only: no X-ray-like image of each predicted shape
        overrides = {**(overrides or {})}
        overrides["virtual"] = {**overrides.get("virtual", {}), "render": False}
        self.ctx = open_run(case, resolve_configs(case, overrides), cache_dir=cache_dir)
        self.reals = {v: stages.real_stage(self.ctx, v) for v in self.views}
        self.mesh = stages.mesh_stage(self.ctx)
        apply_geometry(self.ctx, self.mesh.model, self.views)
        for v, s in self.surrogates.items():
            if s.n_nodes != self.mesh.model.n_nodes:
                raise ConfigError(f"surrogate of {v}: trained on a mesh of {s.n_nodes} nodes, "
                                  f"the case's has {self.mesh.model.n_nodes}; rebuild it with "
                                  "`regtrack surrogate build` on this case and its [model] settings")

    def nominal_D(self) -> dict[str, float] | None:
        """Each view's D when its protocol prescribes it (``target_D``); None when a view
        compresses to a gap (e.g. the DICOM's thickness) or a force, where D is an output."""
        out = {}
        for v in self.views:
            last = [s for s in self.ctx.configs.protocols[v].steps
                    if s.action == "move_plate" and s.plate == "upper"][-1:]
            if not last or last[0].to != "degree":
                return None
            out[v] = float(last[0].target_D)
        return out

    def add_full_runs(self, points: list[dict], D: list[dict[str, float]]) -> None:
        """Refit each view's surrogate with the full simulations at ``points`` (infill
        points, each with its views' D; :meth:`~regtrack.surrogate.model.Surrogate.with_fields`).
        The simulations are those ``regtrack run`` makes with these parameters, so runs
        already made (by the calibration's engine) are read from the stage cache."""
        from regtrack.case import resolve_configs
        from regtrack.pipeline import stages
        from regtrack.pipeline.geometry import apply_geometry
        from regtrack.pipeline.run import open_run
        from regtrack.study.params import apply_point

        case = self.ctx.case
        fields: dict[str, list] = {v: [] for v in self.views}
        for point in points:
            ctx = open_run(case, resolve_configs(case, apply_point({}, point, views=self.views)),
                           cache_dir=self.ctx.cache.root)
            apply_geometry(ctx, self.mesh.model, self.views)
            for v in self.views:
                fields[v].append(stages.simulate_stage(ctx, self.mesh, v).positions
                                 - self.mesh.model.points)
        for v in self.views:
            sur = self.surrogates[v]
            params = [[{**p, "target_D": d[v]}[n] for n in sur.names] for p, d in zip(points, D)]
            self.surrogates[v] = sur.with_fields(np.array(params), np.array(fields[v]))

    def positions(self, view: str, point: dict) -> np.ndarray:
        """Predicted deformed node positions (mm, model frame) of ``view`` at ``point``."""
        return self.mesh.model.points + self.surrogates[view].predict(point)

    def rows(self, point: dict, D: dict[str, float]) -> list[dict]:
        """Metrics rows (one per view) at the parameter ``point`` (the surrogates' names
        except ``target_D``), each view at its compression degree ``D[view]``."""
        from regtrack.pipeline import stages

        out = []
        for v in self.views:
            sur = self.surrogates[v]
            p = {**point, "target_D": D[v]}
            sim = stages.SimOutput(v, "surrogate", Path("."), {"D": D[v]}, [],
                                   self.positions(v, {n: p[n] for n in sur.names}),
                                   self.ctx.configs.protocols[v].angle_deg)
            vm = stages.virtual_stage(self.ctx, self.mesh, sim, v)
            row = stages.align_stage(self.ctx, self.mesh, sim, vm, self.reals[v], v).row
            out.append({**row, "surrogate": True})
        return out
