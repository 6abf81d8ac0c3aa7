"""Calibration of a case's material parameters (c1, nu, optionally friction).

The paper chose c1 and nu by hand from its parametric study (Figure 8): the values that
maximise the registration indicators while the compression degree stays clinical.  This
module automates that choice:

* objective ``S(p) = mean over views of (BS_Av + TS_Av) / 2`` (%, or one indicator alone);
* constraint ``D_lo <= D(p) <= D_hi`` for every view, as the penalty
  ``f(p) = -S(p) + 1000 * max_views max(0, D_lo - D, D - D_hi)`` (D is a fraction; 0.01
  outside the range costs 10 points of S);
* a coarse grid (``grid`` values per parameter, geometric for c1, linear otherwise) run in
  parallel through the study engine, then a bounded local optimiser started at the best
  grid point inside its neighbouring cells: :func:`scipy.optimize.minimize_scalar`
  (``method="bounded"``) for one parameter, Nelder-Mead with bounds for more, in
  coordinates normalised to one grid step;
* sensitivity at the optimum: central differences ``dS/dp`` (one-sided when a neighbour run
  failed, and said so) with a step of 5 % of a grid
  step, and the spread ``max S - min S`` along each parameter's grid line through the best
  grid point.

With per-view surrogates (``regtrack calibrate --surrogate DIR``, :mod:`regtrack.surrogate`;
issue 56, after Han et al. 2012) the grid and the local optimiser are replaced by a search
on the surrogates, refined by full runs:

1. each view's D: the protocol's ``target_D``, or where D is an output (a gap from the
   DICOM's thickness, a force target) one full run at the centre of the box;
2. differential evolution (:func:`regtrack.surrogate.identify.identify`, seeded) on ``f``
   with the rows of :class:`regtrack.surrogate.evaluate.SurrogatePipeline`: the
   predicted compressions run through the same projection, registration and metrics;
3. infill: a full run at the surrogates' optimum (in the first round also one point per
   parameter a tenth of a grid step inside the box, so that the refit matches the full
   model's slopes there too); its displacement fields are added to each surrogate
   (:meth:`~regtrack.surrogate.model.Surrogate.with_fields`), so the refitted surrogate
   reproduces the full model there, and a local search on it restarts from the best full
   run so far (the centre run of step 1 included).  Repeated until that search ends at a
   full run already made (within the full calibration's tolerance, 1/100 of a grid step in
   unit coordinates), at most :data:`MAX_INFILL` rounds;
4. the optimum reported is the best full run.  Around it, on the refitted surrogates: the
   sensitivity (central differences, step 1 % of the box) and each parameter's profile
   interval at the surrogates' score error (``|S_sur - S_full|`` there, at least 0.1
   points: what they cannot resolve) as the optimum's uncertainty.  The optimum's score is
   a full run's; the sensitivity and interval are the surrogates', and the result says so
   (``method`` of each sensitivity).

Parameter values are rounded to 4 significant digits before a run, so the optimiser's
nearby points and every later calibration re-use cached runs.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import optimize

from regtrack.errors import ConfigError, RegtrackError
from regtrack.study.engine import Engine
from regtrack.study.params import check_value
from regtrack.study.runner import FAILED, RunSpec, make_run
from regtrack.study.spec import DEFAULT_RUNNER, CaseRef, case_id_of
from regtrack.surrogate.identify import LOG_PARAMS
from regtrack.surrogate.identify import from_unit as _from_unit
from regtrack.surrogate.identify import to_unit as _to_unit

log = logging.getLogger(__name__)

OBJECTIVES = ("mean", "BS_Av", "TS_Av")
PENALTY = 1000.0  # objective points per unit of D outside the range
FAILED_VALUE = 1e6
MAX_INFILL = 4  # rounds of full runs at the surrogates' optimum before giving up


@dataclass
class Evaluation:
    """One evaluated point: parameters, score S (%), worst D violation, objective f."""

    params: dict
    score: float
    violation: float
    f: float
    rows: list = field(default_factory=list)
    error: str | None = None


@dataclass
class CalibrationResult:
    """Optimum, its metrics, the grid, the optimiser path and the sensitivity."""

    case_id: str
    optimum: Evaluation
    best_grid: Evaluation
    grid: list[Evaluation]
    path: list[Evaluation]
    sensitivity: dict[str, dict]
    bounds: dict[str, tuple[float, float]]
    d_range: tuple[float, float]
    objective: str
    computed: int = 0
    cached: int = 0
    surrogate: dict | None = None

    @property
    def feasible(self) -> bool:
        return self.optimum.violation == 0.0 and self.optimum.error is None


def _round(x: float) -> float:
    return float(f"{x:.4g}")


def score_rows(rows: list[dict], *, objective: str) -> tuple[float, list[float]]:
    """S (%) and the D of each view from a run's rows; NaN when a metric is missing."""
    vals, ds = [], []
    for r in rows:
        bs, ts = r.get("BS_Av"), r.get("TS_Av")
        if objective == "mean":
            v = (bs + ts) / 2 if bs is not None and ts is not None else math.nan
        else:
            v = r.get(objective) if r.get(objective) is not None else math.nan
        vals.append(float(v))
        ds.append(float(r["D"]) if r.get("D") is not None else math.nan)
    return (float(np.mean(vals)) if vals else math.nan), ds


def evaluate(outcome: dict, params: dict, *, objective: str,
             d_range: tuple[float, float]) -> Evaluation:
    """Objective value of one run outcome (penalised; failed runs get a huge value)."""
    if outcome["status"] == FAILED:
        return Evaluation(params, math.nan, math.inf, FAILED_VALUE, error=outcome.get("error"))
    score, ds = score_rows(outcome["rows"], objective=objective)
    lo, hi = d_range
    viol = max((max(0.0, lo - d, d - hi) if math.isfinite(d) else math.inf) for d in ds)
    f = -score + PENALTY * viol if math.isfinite(score) and math.isfinite(viol) else FAILED_VALUE
    return Evaluation(params, score, viol, f, rows=outcome["rows"])


def grid_values(name: str, lo: float, hi: float, n: int) -> list[float]:
    """``n`` grid values on [lo, hi]: geometric for c1, linear otherwise (4 digits)."""
    fn = np.geomspace if name in LOG_PARAMS else np.linspace
    return [_round(v) for v in fn(lo, hi, n)]


def _check_bounds(bounds: dict, fixed: dict) -> None:
    problems = []
    if not bounds:
        problems.append("calibrate: no parameter to calibrate; give at least one range "
                        "(--c1 LO HI, --nu LO HI or --friction LO HI)")
    for name, (lo, hi) in bounds.items():
        if name in fixed:
            problems.append(f"calibrate: {name} is both calibrated and fixed; drop one")
        if not lo < hi:
            problems.append(f"calibrate --{name} {lo} {hi}: the lower bound must be below the upper")
        for v in (lo, hi):
            problems += check_value(name, v, where="calibrate")[1]
    for name, v in fixed.items():
        problems += check_value(name, v, where="calibrate --fix")[1]
    if problems:
        raise ConfigError("; ".join(problems))


class _Problem:
    """Runs points of one case through the engine, memoising evaluations."""

    def __init__(self, engine: Engine, case: CaseRef, *, fixed: dict, views, runner, cache_dir,
                 objective: str, d_range: tuple[float, float]):
        from regtrack.pipeline.cache import file_digest

        self.engine, self.case, self.fixed = engine, case, fixed
        self.views, self.runner, self.cache_dir = tuple(views), runner, Path(cache_dir)
        self.objective, self.d_range = objective, d_range
        self.digest = file_digest(case.case_dir)
        self.memo: dict[tuple, Evaluation] = {}
        self.computed = self.cached = 0

    def _spec(self, point: dict, index: int) -> RunSpec:
        return make_run(self.case, self.digest, {**self.fixed, **point}, base={},
                        views=self.views, runner=self.runner, cache_dir=self.cache_dir,
                        index=index)

    def run(self, points: list[dict], *, label: str) -> list[Evaluation]:
        points = [{k: _round(v) for k, v in p.items()} for p in points]
        todo = [p for p in points if tuple(sorted(p.items())) not in self.memo]
        if todo:
            specs = [self._spec(p, i) for i, p in enumerate(todo)]
            ex = self.engine.run(specs, label=label)
            self.computed += len(ex.computed)
            self.cached += len(ex.cached)
            for p, s in zip(todo, specs):
                self.memo[tuple(sorted(p.items()))] = evaluate(
                    ex.outcomes[s.run_key], p, objective=self.objective, d_range=self.d_range)
        return [self.memo[tuple(sorted(p.items()))] for p in points]


def _local_search(prob: _Problem, start: Evaluation, bounds: dict, grid: int,
                  max_evals: int) -> list[Evaluation]:
    names = list(bounds)
    step = 1.0 / (grid - 1)
    t0 = np.array([_to_unit(n, start.params[n], *bounds[n]) for n in names])
    box = [(max(0.0, t - step), min(1.0, t + step)) for t in t0]
    path: list[Evaluation] = []

    def f(t) -> float:
        t = np.atleast_1d(t)
        point = {n: _from_unit(n, float(ti), *bounds[n]) for n, ti in zip(names, t)}
        ev = prob.run([point], label="calibrate: optimiser")[0]
        path.append(ev)
        return ev.f

    if len(names) == 1:
        optimize.minimize_scalar(f, bounds=box[0], method="bounded",
                                 options={"xatol": step / 100, "maxiter": max_evals})
    else:
        simplex = [t0] + [np.clip(t0 + np.eye(len(names))[i] * step / 2 * (1 if t0[i] < 0.5 else -1),
                                  0, 1) for i in range(len(names))]
        optimize.minimize(f, t0, method="Nelder-Mead", bounds=box,
                          options={"initial_simplex": np.array(simplex), "xatol": step / 100,
                                   "fatol": 1e-3, "maxfev": max_evals})
    return path


def _sensitivity(prob: _Problem, best: Evaluation, best_grid: Evaluation,
                 grid_evals: list[Evaluation], bounds: dict, grid: int) -> dict[str, dict]:
    out: dict[str, dict] = {}
    evs = prob.run(_neighbours(best.params, bounds, grid), label="calibrate: sensitivity")
    for i, n in enumerate(bounds):
        line = [e.score for e in grid_evals
                if all(e.params[m] == best_grid.params[m] for m in bounds if m != n)
                and math.isfinite(e.score)]
        out[n] = {**slope(evs[2 * i], best, evs[2 * i + 1], n),
                  "grid_spread": (max(line) - min(line)) if len(line) > 1 else math.nan}
    return out


def _surrogate_sensitivity(info: dict, bounds: dict) -> dict[str, dict]:
    """``dS/dp`` at the optimum on the refitted surrogates (the search's objective is
    ``-S`` inside the D range, so its slope changes sign)."""
    out = {}
    for n, (lo, hi) in bounds.items():
        x, h = info["optimum"][n], 0.01 * (hi - lo)  # the step of identify.profile
        out[n] = {"dS_dparam": -float(info["sensitivity"][n]),
                  "step": min(hi, x + h) - max(lo, x - h),
                  "method": "central, on the refitted surrogates", "grid_spread": math.nan}
    return out


def slope(ea: Evaluation, best: Evaluation, eb: Evaluation, name: str) -> dict:
    """``dS/d(name)`` from the runs below (``ea``) and above (``eb``) the optimum: central
    difference; one-sided against the optimum when one of them failed; NaN with the reason
    when both did (or the optimum did).  Returns ``dS_dparam``, ``step`` and ``method``."""
    ok_a, ok_b, ok_0 = (math.isfinite(e.score) for e in (ea, eb, best))
    if ok_a and ok_b and eb.params[name] != ea.params[name]:
        lo, hi, how = ea, eb, "central"
    elif ok_0 and (ok_a or ok_b):
        lo, hi = (ea, best) if ok_a else (best, eb)
        bad = eb if ok_a else ea
        how = f"one-sided: the run at {name} = {bad.params[name]:.4g} failed"
    else:
        bad = [f"{e.params[name]:.4g}" for e in (ea, eb) if not math.isfinite(e.score)]
        return {"dS_dparam": math.nan, "step": eb.params[name] - ea.params[name],
                "method": f"not available: the runs at {name} = {', '.join(bad) or 'the optimum'} failed"}
    step = hi.params[name] - lo.params[name]
    return {"dS_dparam": (hi.score - lo.score) / step, "step": step, "method": how}


def _check_surrogates(surrogates: dict, bounds: dict, fixed: dict, views) -> None:
    """One line before any run: every view has a surrogate that takes exactly the
    calibrated and fixed parameters (and D), and whose box holds the calibrated ranges."""
    problems = []
    for v in views:
        sur = surrogates.get(v)
        if sur is None:
            problems.append(f"calibrate --surrogate: none of the surrogates is of view {v}; "
                            f"build one with `regtrack surrogate build CASE --view {v.lower()}`")
            continue
        need = set(sur.names) - {"target_D"}
        given = set(bounds) | set(fixed)
        if need != given:
            problems.append(f"calibrate --surrogate ({v}): the surrogate takes "
                            f"{', '.join(sorted(need))}; calibrate or --fix exactly those "
                            f"(got {', '.join(sorted(given)) or 'none'})")
            continue
        for n, (lo, hi) in bounds.items():
            i = sur.names.index(n)
            if lo < sur.lower[i] - 1e-12 or hi > sur.upper[i] + 1e-12:
                problems.append(f"calibrate --{n} {lo:g} {hi:g}: outside the {v} surrogate's "
                                f"range {sur.lower[i]:g} to {sur.upper[i]:g}; narrow it or "
                                "rebuild the surrogate")
    if problems:
        raise ConfigError("; ".join(problems))


def _neighbours(point: dict, bounds: dict, grid: int) -> list[dict]:
    """The sensitivity's points around ``point``: each parameter moved by 5 % of a grid step
    (unit coordinates) down and up, in :func:`_sensitivity`'s order."""
    out = []
    for n, (lo, hi) in bounds.items():
        t, h = _to_unit(n, point[n], lo, hi), 0.05 / (grid - 1)
        out += [{**point, n: _from_unit(n, t - h, lo, hi)}, {**point, n: _from_unit(n, t + h, lo, hi)}]
    return out


def _forward(point: dict, bounds: dict, grid: int) -> list[dict]:
    """One point per parameter, moved by a tenth of a grid step (unit coordinates) towards
    the inside of the box."""
    out = []
    for n, (lo, hi) in bounds.items():
        t, h = _to_unit(n, point[n], lo, hi), 0.1 / (grid - 1)
        out.append({**point, n: _round(_from_unit(n, t + h if t <= 0.5 else t - h, lo, hi))})
    return out


def _surrogate_search(prob: _Problem, surrogates: dict, bounds: dict, grid: int
                      ) -> tuple[Evaluation, list[Evaluation], dict]:
    """Steps 1-3 of the module docstring; returns the first full run, the full runs at the
    surrogates' optima and the record of the search."""
    from regtrack.case import load_case
    from regtrack.surrogate.evaluate import SurrogatePipeline
    from regtrack.surrogate.identify import identify, profile, refine

    pipe = SurrogatePipeline(load_case(prob.case.case_dir), {v: surrogates[v] for v in prob.views},
                             cache_dir=prob.cache_dir)
    D = pipe.nominal_D()
    first = None
    if D is None:  # D is an output (a gap or force target): one full run gives it
        centre = {n: _round(_from_unit(n, 0.5, *b)) for n, b in bounds.items()}
        first = prob.run([centre], label="calibrate: centre run (D of each view)")[0]
        if first.error is not None:
            raise ConfigError(f"{prob.case.case_dir}: the full run at the centre of the box "
                              f"failed ({first.error}); run 'regtrack study' on the case to "
                              "see why")
        D = {r["view"]: float(r["D"]) for r in first.rows}
    evals = [0]

    def f(point: dict) -> float:
        evals[0] += 1
        try:
            rows = pipe.rows({**prob.fixed, **point}, D)
        except RegtrackError as err:  # e.g. no registration of a predicted shape: a bad point
            log.debug("surrogate point %s: %s", point, err)
            return FAILED_VALUE
        return evaluate({"status": "ok", "rows": rows}, point, objective=prob.objective,
                        d_range=prob.d_range).f

    def unit(p: dict) -> np.ndarray:
        return np.array([_to_unit(n, p[n], *bounds[n]) for n in bounds])

    xatol = 1.0 / (grid - 1) / 100  # the full calibration's local tolerance
    log.info("calibrate: global search on the surrogates of %s", ", ".join(prob.views))
    ident = identify(f, bounds, tolerance=None, popsize=6, maxiter=10, polish=False)
    infill: list[Evaluation] = []
    rounds: list[dict] = []
    settled = False

    def fulls() -> list[Evaluation]:
        return [e for e in (first, *infill) if e is not None]

    for k in range(MAX_INFILL):
        opt = {n: _round(v) for n, v in ident.params.items()}
        if any(np.abs(unit(opt) - unit(e.params)).max() <= xatol for e in fulls()):
            settled = True  # the refitted surrogates' optimum is a full run already
            break
        # the first round also corrects the surrogates' slopes (a forward point per
        # parameter); later optima lie near earlier full runs, which do that
        pts = [opt, *(_forward(opt, bounds, grid) if not infill else [])]
        evs = prob.run(pts, label=f"calibrate: full runs at the surrogates' optimum ({k + 1})")
        full = evs[0]
        rounds.append({"params": opt, "score_surrogate": -ident.value, "score_full": full.score})
        log.info("calibrate: surrogate optimum %s, S = %.2f %% (full run %.2f %%)", opt,
                 -ident.value, full.score)
        infill.append(full)
        ok = [e for e in evs if e.error is None]
        if full.error is not None:
            break
        D = {r["view"]: float(r["D"]) for r in full.rows}
        # the runs' own (rounded) parameters: the same simulations, found in the stage cache
        pipe.add_full_runs([{**prob.fixed, **e.params} for e in ok],
                           [{r["view"]: float(r["D"]) for r in e.rows} for e in ok])
        best = min(fulls(), key=lambda e: e.f)
        ident = refine(f, bounds, best.params, step=max(4 * xatol, 0.02), xatol=xatol / 2,
                       maxfev=40)
    # the uncertainty around the optimum reported (the best full run), at the surrogates'
    # score error in the best infill round
    i_best = min(range(len(infill)), key=lambda i: infill[i].f)
    s_sur, s_full = rounds[i_best]["score_surrogate"], rounds[i_best]["score_full"]
    tol = max(abs(s_sur - s_full), 0.1) if math.isfinite(s_full) else 0.1
    best = min(fulls(), key=lambda e: e.f)
    ident.params, ident.value = dict(best.params), f(best.params)
    profile(f, ident, bounds, tolerance=tol)
    info = {"views": {v: (surrogates[v].meta.get("validation") or {}).get("held_out", {}).get("pooled")
                      for v in prob.views},
            "D": D, "optimum": ident.params, "score_surrogate": s_sur, "score_full": s_full,
            "score_error": abs(s_sur - s_full), "rounds": rounds, "settled": settled,
            "interval": {k: list(v) for k, v in ident.interval.items()},
            "sensitivity": ident.sensitivity, "tolerance": tol, "evaluations": evals[0]}
    if not settled:
        log.warning("calibrate: the surrogates' optimum still moved after %d rounds of full "
                    "runs; the best of them is reported", len(rounds))
    return (first or infill[0]), infill, info


def calibrate(case_dir: str | Path, *, bounds: dict[str, tuple[float, float]],
              fixed: dict | None = None, views: tuple[str, ...] = ("CC",),
              d_range: tuple[float, float] = (0.2, 0.6), objective: str = "mean",
              grid: int = 4, max_evals: int = 25, runner: str = DEFAULT_RUNNER,
              cache_dir: str | Path, scheduler: str | None = None, workers: int = 0,
              progress: bool = True, surrogates: dict | None = None) -> CalibrationResult:
    """Find the parameters maximising the indicators with D in ``d_range``.

    Parameters
    ----------
    case_dir : path
        The case folder.
    bounds : dict
        Parameter name (see :mod:`regtrack.study.params`) -> (low, high); c1 in kPa.
    fixed : dict, optional
        Parameters held fixed (e.g. ``{"friction": 0.2}``).
    d_range : (float, float)
        Clinical range of the compression degree D (fraction of breast thickness).
    objective : {"mean", "BS_Av", "TS_Av"}
        What to maximise: (BS_Av + TS_Av) / 2 or one indicator (%).
    grid : int
        Grid values per parameter (>= 2); ``grid ** len(bounds)`` runs.
    max_evals : int
        Most runs of the local optimiser.
    surrogates : dict, optional
        View -> :class:`~regtrack.surrogate.model.Surrogate` of every calibrated view: the
        grid is replaced by the global search on them (module docstring).
    """
    fixed = dict(fixed or {})
    _check_bounds(bounds, fixed)
    if objective not in OBJECTIVES:
        raise ConfigError(f"calibrate --objective {objective!r}: use one of {', '.join(OBJECTIVES)}")
    if grid < 2 or not 0 <= d_range[0] < d_range[1] <= 1:
        raise ConfigError(f"calibrate: need --grid >= 2 (got {grid}) and 0 <= D_lo < D_hi <= 1 "
                          f"(got {d_range})")
    case_dir = Path(case_dir).resolve()
    if not (case_dir / "case.toml").is_file():
        raise ConfigError(f"{case_dir}: not a case folder (no case.toml); give a case folder")
    case = CaseRef(case_dir, case_id_of(case_dir))
    if surrogates:
        _check_surrogates(surrogates, bounds, fixed, views)
    sur_info = None
    with Engine(runner=runner, cache_dir=Path(cache_dir), scheduler=scheduler, workers=workers,
                progress=progress) as engine:
        prob = _Problem(engine, case, fixed=fixed, views=views, runner=runner,
                        cache_dir=cache_dir, objective=objective, d_range=d_range)
        if surrogates:
            best_grid, path, sur_info = _surrogate_search(prob, surrogates, bounds, grid)
            grid_evals = [best_grid]
        else:
            axes = {n: grid_values(n, lo, hi, grid) for n, (lo, hi) in bounds.items()}
            points = [dict(zip(axes, combo)) for combo in itertools.product(*axes.values())]
            grid_evals = prob.run(points, label="calibrate: grid")
            best_grid = min(grid_evals, key=lambda e: e.f)
            if best_grid.f >= FAILED_VALUE:
                raise ConfigError(f"{case_dir}: every grid run failed ({best_grid.error}); run "
                                  "'regtrack study' on the case to see why")
            path = _local_search(prob, best_grid, bounds, grid, max_evals)
        best = min([best_grid, *path], key=lambda e: e.f)
        if surrogates:
            sens = _surrogate_sensitivity(sur_info, bounds)
        else:
            sens = _sensitivity(prob, best, best_grid, grid_evals, bounds, grid)
    log.info("calibration of %s: %s S = %.2f %% (violation %.3g); %d runs computed, %d cached",
             case.case_id, best.params, best.score, best.violation, prob.computed, prob.cached)
    return CalibrationResult(case_id=case.case_id, optimum=best, best_grid=best_grid,
                             grid=grid_evals, path=path, sensitivity=sens, bounds=dict(bounds),
                             d_range=tuple(d_range), objective=objective,
                             computed=prob.computed, cached=prob.cached, surrogate=sur_info)


def to_json(result: CalibrationResult) -> dict:
    """JSON-ready summary (NaN/inf become None)."""

    def num(x):
        return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else x

    def ev(e: Evaluation) -> dict:
        return {"params": e.params, "score": num(e.score), "violation": num(e.violation),
                "f": num(e.f), "error": e.error}

    return {"case_id": result.case_id, "objective": result.objective,
            "d_range": list(result.d_range), "bounds": {k: list(v) for k, v in result.bounds.items()},
            "optimum": {**ev(result.optimum), "rows": result.optimum.rows},
            "feasible": result.feasible, "best_grid": ev(result.best_grid),
            "sensitivity": {k: {kk: num(vv) for kk, vv in s.items()}
                            for k, s in result.sensitivity.items()},
            "grid": [ev(e) for e in result.grid], "path": [ev(e) for e in result.path],
            "runs_computed": result.computed, "runs_cached": result.cached,
            "surrogate": None if result.surrogate is None else {
                k: (num(v) if isinstance(v, float) else v) for k, v in result.surrogate.items()}}
