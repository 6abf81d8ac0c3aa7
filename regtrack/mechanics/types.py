"""Plain records passed out of the mechanics solver."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class StepStats:
    """Counts and times of one load step (pseudo-time 0 -> 1) of the energy solver
    (:mod:`.minimise`); ``to_dict`` is what a protocol step records.

    ``increments`` accepted and ``cutbacks`` halved increments, ``iterations`` Newton
    iterations, ``augmentations`` multiplier / friction-lag updates; ``factorisations``
    sparse factorisations and ``krylov_solves`` solves on a re-used one (:mod:`.linsolve`);
    ``inertia_corrections`` Hessians made positive definite, ``rejected_directions``
    corrections of an old factorisation that did not descend, ``line_search_trials``
    potential evaluations of the line search, ``ccd_limited`` line searches started
    below the full step so that no node crosses the outer surface (:mod:`.selfcontact`).  Times are wall-clock seconds:
    ``t_assembly`` (tissue, skin and contact terms), ``t_solve`` (linear solves),
    ``t_total``.
    """

    name: str = ""
    increments: int = 0
    iterations: int = 0
    cutbacks: int = 0
    augmentations: int = 0
    factorisations: int = 0
    krylov_solves: int = 0
    inertia_corrections: int = 0
    rejected_directions: int = 0
    line_search_trials: int = 0
    ccd_limited: int = 0
    t_assembly: float = 0.0
    t_solve: float = 0.0
    t_total: float = 0.0
    reports: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "reports"}


@dataclass
class SolverStats:
    """Totals over all steps of a run."""

    steps: list[StepStats] = field(default_factory=list)

    def total(self, name: str) -> float:
        """Sum of the :class:`StepStats` field ``name`` over the steps."""
        return sum(getattr(s, name) for s in self.steps)

    def to_dict(self) -> dict:
        return {"steps": len(self.steps), "increments": self.total("increments"),
                "iterations": self.total("iterations"), "cutbacks": self.total("cutbacks"),
                "t_total_s": self.total("t_total"), "t_assembly_s": self.total("t_assembly"),
                "t_solve_s": self.total("t_solve")}


@dataclass
class StepResult:
    """State at the end of a step: displacement (N, 3) mm and reaction at constrained dofs.

    ``reaction`` (N, 3) N is the force the supports exert on the body (zero at free
    dofs); ``chest_wall_reaction_n`` is its sum over the model's fixed (chest-wall) nodes.
    """

    name: str
    u: np.ndarray
    reaction: np.ndarray
    chest_wall_reaction_n: np.ndarray
    stats: StepStats


@dataclass
class Deformation:
    """Result of :func:`regtrack.mechanics.steps.run_steps`: one :class:`StepResult` per step."""

    steps: list[StepResult]
    stats: SolverStats
    config: dict = field(default_factory=dict)

    @property
    def u(self) -> np.ndarray:
        """Final displacement (N, 3), mm."""
        return self.steps[-1].u
