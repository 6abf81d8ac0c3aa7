"""Simulation configs (TOML) and :func:`run_steps`: a sequence of load steps -> Deformation.

Format (the file-level contract of ``regtrack simulate --model M.vtu --config C.toml``)::

    [mechanics]                 # MechanicsConfig overrides (kPa, Pa, mm), [mechanics.solver]
    nu = 0.49

    [[steps]]
    name = "gravity"            # optional, default "step<k>"
    kind = "gravity"            # body force rho * g, g = vector_ms2 * scale
    vector_ms2 = [0.0, -9.81, 0.0]   # model frame (x anterior, y superior, z right)
    from_scale = 0.0            # scale at the start of the step (default: current)
    to_scale = 1.0              # scale at its end

    [[steps]]
    kind = "displacement"       # prescribed displacement increment of a node set
    node_set = "tip"            # "fixed", "all", or a point-data field of the model (nonzero = in)
    vector_mm = [0.0, 0.0, -5.0]
    components = [true, true, true]   # which components are prescribed (default all)

Gravity stays at its last value in later steps; a displaced node set stays held.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from regtrack.config import parse_section
from regtrack.errors import ConfigError
from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.problem import Problem, reaction_forces
from regtrack.mechanics.types import Deformation, SolverStats, StepResult

log = logging.getLogger(__name__)

KINDS = ("gravity", "displacement")


@dataclass(frozen=True)
class LoadStep:
    """One load step (see the module docstring for the TOML keys)."""

    name: str
    kind: str
    vector: tuple[float, float, float]
    from_scale: float | None = None
    to_scale: float = 1.0
    node_set: str = ""
    components: tuple[bool, bool, bool] = (True, True, True)


def _vec(v, where: str, key: str) -> tuple[float, float, float]:
    if (not isinstance(v, (list, tuple)) or len(v) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
        raise ConfigError(f"{where} {key} = {v!r}: expected three numbers [x, y, z] (model frame)")
    return tuple(float(x) for x in v)  # type: ignore[return-value]


def parse_steps(table: list | None, *, where: str = "config [[steps]]") -> list[LoadStep]:
    """Validate the ``[[steps]]`` array of tables; errors name the step index and key."""
    if not table:
        raise ConfigError(f"{where}: no steps; add at least one [[steps]] table with kind = 'gravity' "
                          "or 'displacement'")
    out = []
    for k, st in enumerate(table, start=1):
        w = f"{where}[{k}]"
        if not isinstance(st, dict):
            raise ConfigError(f"{w}: expected a table")
        kind = st.get("kind")
        if kind not in KINDS:
            raise ConfigError(f"{w} kind = {kind!r}: must be one of {', '.join(KINDS)}")
        allowed = {"name", "kind", "vector_ms2", "from_scale", "to_scale"} if kind == "gravity" else \
            {"name", "kind", "node_set", "vector_mm", "components"}
        unknown = set(st) - allowed
        if unknown:
            raise ConfigError(f"{w}: unknown key(s) {', '.join(sorted(unknown))} for kind '{kind}' "
                              f"(valid: {', '.join(sorted(allowed))})")
        name = str(st.get("name", f"step{k}"))
        if kind == "gravity":
            for key in ("from_scale", "to_scale"):
                if key in st and (isinstance(st[key], bool) or not isinstance(st[key], (int, float))):
                    raise ConfigError(f"{w} {key} = {st[key]!r}: expected a number")
            out.append(LoadStep(name, kind, _vec(st.get("vector_ms2", [0, -9.81, 0]), w, "vector_ms2"),
                                None if "from_scale" not in st else float(st["from_scale"]),
                                float(st.get("to_scale", 1.0))))
        else:
            if not isinstance(st.get("node_set"), str):
                raise ConfigError(f"{w} node_set: required; give 'fixed', 'all' or a point-data field name")
            comps = st.get("components", [True, True, True])
            if not (isinstance(comps, list) and len(comps) == 3 and all(isinstance(c, bool) for c in comps)):
                raise ConfigError(f"{w} components = {comps!r}: expected three booleans")
            out.append(LoadStep(name, kind, _vec(st.get("vector_mm"), w, "vector_mm"),
                                node_set=st["node_set"], components=tuple(comps)))  # type: ignore[arg-type]
    return out


def parse_simulation(doc: dict, *, where: str = "config") -> tuple[MechanicsConfig, list[LoadStep], list[str]]:
    """``(MechanicsConfig, steps, warnings)`` from a parsed simulation TOML."""
    unknown = set(doc) - {"mechanics", "steps"}
    warnings = [f"{where}: unknown section [{u}] ignored" for u in sorted(unknown)]
    mech, problems, w = parse_section(MechanicsConfig, doc.get("mechanics"), where=f"{where} [mechanics]")
    if problems:
        raise ConfigError("; ".join(problems))
    return mech, parse_steps(doc.get("steps"), where=f"{where} [[steps]]"), warnings + w


def node_set_mask(name: str, problem: Problem, fields: dict[str, np.ndarray], *, where: str) -> np.ndarray:
    if name == "fixed":
        return problem.model.fixed.copy()
    if name == "all":
        return np.ones(problem.n_nodes, bool)
    if name not in fields:
        raise ConfigError(f"{where} node_set = {name!r}: no such point-data field in the model "
                          f"(available: {', '.join(['fixed', 'all', *sorted(fields)])})")
    return np.asarray(fields[name]).reshape(problem.n_nodes, -1)[:, 0] != 0


def run_steps(problem: Problem, steps: list[LoadStep], *, node_sets: dict[str, np.ndarray] | None = None,
              progress: Callable[[str, float], None] | None = None, where: str = "config [[steps]]") -> Deformation:
    """Run ``steps`` in order from the undeformed state; one :class:`StepResult` per step.

    Each step is a minimisation of the incremental potential (:func:`.minimise.minimise_step`)
    in ``1 / [mechanics.solver] initial_increment`` increments.

    The reaction of each step (``reaction``, N) is the force the supports (fixed nodes and
    prescribed node sets) exert on the body; ``chest_wall_reaction_n`` sums it over the
    model's fixed (chest-wall) nodes.
    """
    fields = node_sets or {}
    n_increments = int(np.ceil(1.0 / problem.config.solver.initial_increment - 1e-9))
    u = np.zeros_like(problem.X)
    g_vec, g_scale = np.zeros(3), 0.0
    held: dict[int, float] = {}
    results, stats = [], SolverStats()
    for k, st in enumerate(steps, start=1):
        w = f"{where}[{k}]"
        if st.kind == "gravity":
            g0 = g_vec * g_scale
            s0 = g_scale if st.from_scale is None else st.from_scale
            v = np.asarray(st.vector)
            if st.from_scale is not None:
                g0 = v * s0
            g1 = v * st.to_scale

            def gravity(t, g0=g0, g1=g1):
                return g0 + t * (g1 - g0)

            g_vec, g_scale = v, st.to_scale
            dirichlet = _held(held, None)
        else:
            g_now = g_vec * g_scale

            def gravity(t, g_now=g_now):
                return g_now

            mask = node_set_mask(st.node_set, problem, fields, where=w)
            nodes = np.flatnonzero(mask)
            comps = np.flatnonzero(st.components)
            dofs = (3 * nodes[:, None] + comps[None, :]).reshape(-1)
            start = u.reshape(-1)[dofs]
            inc = np.tile(np.asarray(st.vector)[comps], len(nodes))
            dirichlet = _held(held, (dofs, start, inc))
            for d, val in zip(dofs, start + inc):
                held[int(d)] = float(val)
        u, sstats, _ = minimise_step(problem, u, gravity=gravity, dirichlet=dirichlet,
                                     n_increments=n_increments, step_name=st.name,
                                     progress=progress)
        _check_state(problem, u, st.name)
        R = reaction_forces(problem, u, gravity_ms2=gravity(1.0))
        cons = np.zeros(problem.n_dofs, bool)
        cons[problem.fixed_dofs] = True
        cons[list(held)] = True
        R = np.where(cons.reshape(-1, 3), R, 0.0)
        results.append(StepResult(st.name, u.copy(), R, R[problem.model.fixed].sum(axis=0), sstats))
        stats.steps.append(sstats)
        log.info("step %s: %d increments, %d iterations, chest-wall reaction %s N", st.name,
                 sstats.increments, sstats.iterations, np.round(results[-1].chest_wall_reaction_n, 6))
    return Deformation(results, stats)


def _check_state(problem: Problem, u: np.ndarray, name: str) -> None:
    """Guard rail: a returned state is finite and has no inverted element."""
    from regtrack.errors import ResultCheckError
    from regtrack.mechanics.problem import evaluate

    if not np.all(np.isfinite(u)):
        raise ResultCheckError(f"step '{name}': non-finite displacements; the result was not written")
    ev = evaluate(problem, u, want_k=False)
    if ev.n_inverted:
        raise ResultCheckError(f"step '{name}': {ev.n_inverted} inverted elements in the converged state; "
                               "refine the mesh or reduce the load")


def _held(held: dict[int, float], new):
    """Dirichlet callable: held node sets at their values, plus a new ramp (dofs, start, inc)."""
    hd = np.array(sorted(held), np.int64)
    hv = np.array([held[d] for d in hd]) if len(hd) else np.zeros(0)
    if new is None:
        return (lambda t: (hd, hv)) if len(hd) else None
    dofs, start, inc = new
    keep = ~np.isin(hd, dofs)
    hd, hv = hd[keep], hv[keep]

    def dirichlet(t):
        return np.concatenate([hd, dofs]), np.concatenate([hv, start + t * inc])

    return dirichlet


def simulate(model, config: MechanicsConfig | None = None, steps: list[LoadStep] | None = None, *,
             node_sets: dict[str, np.ndarray] | None = None,
             progress: Callable[[str, float], None] | None = None) -> Deformation:
    """Plain function API: ``model`` (BreastModel) + ``config`` + ``steps`` -> :class:`Deformation`.

    Defaults: :class:`MechanicsConfig` () and one standing-gravity step (-y, 9.81 m/s^2).
    """
    from regtrack.config import to_table
    from regtrack.mechanics.problem import build_problem

    config = config or MechanicsConfig()
    steps = steps or [LoadStep("gravity", "gravity", (0.0, -9.81, 0.0), 0.0, 1.0)]
    deformation = run_steps(build_problem(model, config), steps, node_sets=node_sets, progress=progress)
    deformation.config = {"mechanics": to_table(config), "steps": [s.__dict__ for s in steps]}
    return deformation
