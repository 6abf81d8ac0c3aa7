"""Plain records passed out of the mechanics solver."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class StepStats:
    """Statistics of one protocol/load step (pseudo-time 0 -> 1).

    Times are wall-clock seconds per phase: ``t_assembly`` (tissue + skin residual and
    tangent), ``t_contrib`` (contributions such as contact), ``t_solve`` (sparse
    factorisation + solve), ``t_line_search`` (extra residual evaluations), ``t_total``;
    ``cpu_total`` is the process CPU time of the step (all threads; s).  ``factorisations``
    counts sparse factorisations, ``krylov_solves`` the solves done on a re-used one and
    ``krylov_iterations`` all GMRES iterations (:mod:`.linsolve`), ``reuse_failures`` the
    re-used factorisations given up for a fresh one and ``krylov_wasted_iterations`` the
    GMRES iterations spent on them.  ``stabilised_increments``
    counts the stabilised retries of failed increments (successful or not),
    ``stabilised_accepted`` the accepted increments that needed one (settled or not) and
    ``longest_stabilised_run`` the most of those in a row (the crawl guard's measure),
    ``settled_increments`` those whose state an undamped solve at the same load then made an
    equilibrium, ``failed_undamped_iterations`` the Newton iterations of undamped solves that
    failed (first attempts before a stabilised retry, and settles after one),
    ``skipped_undamped`` the increments of a stabilised run solved stabilised at once
    (``[mechanics.solver] stabilised_first_after``), ``skipped_settles`` those of them
    committed stabilised without a settle (``stabilised_skip_settle``), and
    ``polish_solves`` the undamped solves at t = 1 after a stabilised last increment
    (:mod:`.solver`); ``stalled_augmentations`` the increments cut back because a
    contribution's multipliers stopped converging (:meth:`.contact.PlateContact.augment`);
    ``tightening_solves`` the solves to ``force_tol`` of increments whose multiplier
    iterations used inexact solves (``augmentation_force_tol``); ``increment_refactors``
    the increments whose first linear solve was factorised afresh by
    ``[mechanics.solver] increment_refactor`` (:mod:`.solver`);
    ``extrapolated_increments`` counts the increments whose Newton
    iterations started from the linear extrapolation of the previous increment.
    ``line_search_trials`` counts the line-search residual evaluations and
    ``inverted_trials`` those rejected because an element inverted there (the step is then
    halved).  On the benchmark hemisphere's CC compression the inverted elements lie
    under the plates next to the fixed chest wall.
    """

    name: str = ""
    increments: int = 0
    iterations: int = 0
    cutbacks: int = 0
    augmentations: int = 0
    extra_iterations: int = 0
    freezes: int = 0
    stalled_accepts: int = 0
    stalled_residual_max: float = 0.0
    stalled_augmentations: int = 0
    tightening_solves: int = 0
    merit_retries: int = 0
    tangent_retries: int = 0
    stabilised_increments: int = 0
    stabilised_accepted: int = 0
    longest_stabilised_run: int = 0
    settled_increments: int = 0
    failed_undamped_iterations: int = 0
    skipped_settles: int = 0
    skipped_undamped: int = 0
    polish_solves: int = 0
    extrapolated_increments: int = 0
    line_search_trials: int = 0
    inverted_trials: int = 0
    factorisations: int = 0
    analyses: int = 0
    krylov_solves: int = 0
    krylov_iterations: int = 0
    reuse_failures: int = 0
    krylov_wasted_iterations: int = 0
    increment_refactors: int = 0
    t_assembly: float = 0.0
    t_contrib: float = 0.0
    t_solve: float = 0.0
    t_line_search: float = 0.0
    t_total: float = 0.0
    cpu_total: float = 0.0
    residual_history: list[list[float]] = field(default_factory=list)
    reports: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        keys = ("name", "increments", "iterations", "cutbacks", "augmentations", "extra_iterations",
                "freezes", "stalled_accepts", "stalled_residual_max", "stalled_augmentations",
                "tightening_solves", "merit_retries", "tangent_retries", "stabilised_increments",
                "stabilised_accepted", "longest_stabilised_run", "settled_increments",
                "failed_undamped_iterations", "skipped_undamped", "skipped_settles",
                "polish_solves", "extrapolated_increments",
                "line_search_trials", "inverted_trials", "factorisations", "analyses",
                "krylov_solves", "krylov_iterations", "reuse_failures", "krylov_wasted_iterations",
                "increment_refactors", "t_assembly", "t_contrib", "t_solve", "t_line_search",
                "t_total", "cpu_total")
        d = {k: getattr(self, k) for k in keys}
        d["reports"] = self.reports[-1:] if self.reports else []
        return d


@dataclass
class SolverStats:
    """Totals over all steps of a run."""

    steps: list[StepStats] = field(default_factory=list)

    @property
    def iterations(self) -> int:
        return sum(s.iterations for s in self.steps)

    @property
    def increments(self) -> int:
        return sum(s.increments for s in self.steps)

    @property
    def cutbacks(self) -> int:
        return sum(s.cutbacks for s in self.steps)

    @property
    def time_total(self) -> float:
        return sum(s.t_total for s in self.steps)

    def to_dict(self) -> dict:
        return {"steps": len(self.steps), "increments": self.increments, "iterations": self.iterations,
                "cutbacks": self.cutbacks, "t_total_s": self.time_total,
                "t_assembly_s": sum(s.t_assembly for s in self.steps),
                "t_solve_s": sum(s.t_solve for s in self.steps),
                "t_contrib_s": sum(s.t_contrib for s in self.steps),
                "t_line_search_s": sum(s.t_line_search for s in self.steps)}


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
    """Result of :func:`regtrack.mechanics.solver.run_steps`: one :class:`StepResult` per step."""

    steps: list[StepResult]
    stats: SolverStats
    config: dict = field(default_factory=dict)

    @property
    def u(self) -> np.ndarray:
        """Final displacement (N, 3), mm."""
        return self.steps[-1].u
