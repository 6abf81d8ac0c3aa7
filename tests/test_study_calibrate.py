"""Calibration (coarse grid + bounded optimiser) on the fake pipeline, whose optimum is known.

The fake score S = (BS_Av + TS_Av)/2 = 86 - 10 ln(c1/0.8)^2 - 5e4 (nu - 0.47)^2 - 2.5 friction
peaks at c1 = 0.8 kPa, nu = 0.47; its D = 0.45 - 0.1 ln(c1/0.54) (tests/_study_fakes.py).
Tolerances: parameters are rounded to 4 significant digits and the optimiser stops at
1/100 of a grid step, within 40 evaluations; 1 % on c1 and 0.001 on nu are a few such steps.
"""

from __future__ import annotations

import json
import math

import pytest

from regtrack.cli import main
from regtrack.errors import ConfigError
from regtrack.study.calibrate import calibrate, to_json
from tests._study_fakes import make_case

FAKE = "fake"  # registered by tests._study_fakes


def test_finds_known_optimum_and_reuses_cache(tmp_path):
    case = make_case(tmp_path, "A")
    kw = dict(bounds={"c1": (0.2, 3.0), "nu": (0.45, 0.49)}, runner=FAKE,
              cache_dir=tmp_path / "cache", workers=2, progress=False, max_evals=40)
    res = calibrate(case, **kw)
    assert res.optimum.params["c1"] == pytest.approx(0.8, rel=0.01)
    assert res.optimum.params["nu"] == pytest.approx(0.47, abs=1e-3)
    assert res.feasible and res.optimum.score >= res.best_grid.score
    assert len(res.grid) == 16 and res.cached == 0
    # at the optimum the score is flat in c1; the grid spread shows c1 matters over the range
    assert abs(res.sensitivity["c1"]["dS_dparam"]) < 1.0
    assert res.sensitivity["c1"]["grid_spread"] > 10
    again = calibrate(case, **kw)
    assert again.computed == 0 and again.cached == res.computed
    assert again.optimum.params == res.optimum.params


def test_compression_constraint_is_respected(tmp_path):
    case = make_case(tmp_path, "A")
    # D >= 0.43 <=> c1 <= 0.54 exp(0.2) = 0.6596 kPa: the optimum moves onto that bound
    res = calibrate(case, bounds={"c1": (0.2, 3.0)}, fixed={"nu": 0.47}, d_range=(0.43, 0.6),
                    runner=FAKE, cache_dir=tmp_path / "cache", workers=1, progress=False)
    c1_bound = 0.54 * math.exp(0.2)
    assert res.optimum.params["c1"] == pytest.approx(c1_bound, rel=0.01)
    assert res.optimum.rows[0]["D"] >= 0.43 - 1e-3
    assert any(e.violation > 0 for e in res.grid)


def test_cli_writes_json_and_figure(tmp_path):
    case = make_case(tmp_path, "A")
    rc = main(["-q", "calibrate", str(case), "--runner", FAKE, "--fix", "nu=0.47",
               "--friction", "0.0", "0.4", "--grid", "3", "--no-progress", "--workers", "1",
               "--out", str(tmp_path / "cal")])
    assert rc == 0
    out = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    assert set(out["optimum"]["params"]) == {"c1", "friction"}
    assert out["optimum"]["params"]["friction"] == pytest.approx(0.0, abs=0.01)  # S falls with friction
    assert (tmp_path / "cal" / "calibration.png").stat().st_size > 1000


@pytest.mark.parametrize("kw, match", [
    (dict(bounds={"c1": (2.0, 1.0)}), "lower bound must be below"),
    (dict(bounds={"nu": (0.45, 0.5)}), "nu = 0.5: must be < 0.5"),
    (dict(bounds={}), "no parameter to calibrate"),
    (dict(bounds={"c1": (0.2, 2.0)}, objective="max"), "--objective 'max'"),
])
def test_bad_calibration_requests(tmp_path, kw, match):
    case = make_case(tmp_path, "A")
    with pytest.raises(ConfigError, match=match):
        calibrate(case, runner=FAKE, cache_dir=tmp_path / "c", progress=False, **kw)
    assert not (tmp_path / "c").exists()


def test_sensitivity_survives_failed_neighbour_runs():
    from regtrack.study.calibrate import Evaluation, slope

    def ev(c1, score):
        return Evaluation(params={"c1": c1}, score=score, violation=0.0, f=-score)

    nan = math.nan
    central = slope(ev(0.9, 70.0), ev(1.0, 80.0), ev(1.1, 74.0), "c1")
    assert central["dS_dparam"] == pytest.approx(20.0) and central["method"] == "central"
    up = slope(ev(0.9, nan), ev(1.0, 80.0), ev(1.1, 74.0), "c1")
    assert up["dS_dparam"] == pytest.approx(-60.0) and "c1 = 0.9 failed" in up["method"]
    down = slope(ev(0.9, 70.0), ev(1.0, 80.0), ev(1.1, nan), "c1")
    assert down["dS_dparam"] == pytest.approx(100.0) and "c1 = 1.1 failed" in down["method"]
    none = slope(ev(0.9, nan), ev(1.0, 80.0), ev(1.1, nan), "c1")
    assert math.isnan(none["dS_dparam"]) and none["method"].startswith("not available")
    assert "0.9, 1.1" in none["method"]


class _FakeSurrogate:
    """Stands for a fitted surrogate of one view: its names, box and validation record."""

    def __init__(self, view):
        self.names = ("c1", "nu", "target_D")
        self.lower, self.upper = (0.2, 0.45, 0.2), (3.0, 0.49, 0.6)
        self.meta = {"validation": {"view": view, "held_out": {"pooled": {"median_mm": 0.2}}}}


def _fake_surrogate_pipeline(monkeypatch, calls):
    """The surrogate path's pipeline replaced by the fake metrics plus a known, smooth
    surrogate error e(p) = 0.3 sin(5 c1) score points, so the first search lands near, not
    at, the optimum.  Infill points correct it as refitting an interpolating surrogate
    does: the error left is e minus its Gaussian-process interpolant through the infill
    points (squared-exponential correlation, length 0.15 in the unit coordinates)."""
    import numpy as np

    import regtrack.case
    import regtrack.surrogate.evaluate as ev
    from tests._study_fakes import metrics

    def unit(p):
        return np.array([math.log(p["c1"] / 0.2) / math.log(15.0), (p["nu"] - 0.45) / 0.04])

    def e0(p):
        return 0.3 * math.sin(5 * p["c1"])

    def k(a, b):
        return math.exp(-float(np.sum((a - b) ** 2)) / 0.15 ** 2)

    class Pipe:
        def __init__(self, case, surrogates, **kw):
            self.views = tuple(surrogates)
            self.points = []

        def nominal_D(self):
            return None  # the fake's D depends on c1: one full run at the centre gives it

        def add_full_runs(self, points, D):
            # the runs' own parameters (4 digits), so the real pipeline finds their
            # simulations in the stage cache instead of simulating again
            assert all(v == float(f"{v:.4g}") for p in points for v in p.values())
            self.points += [dict(p) for p in points]

        def error(self, point):
            if not self.points:
                return e0(point)
            q = [unit(p) for p in self.points]
            K = np.array([[k(a, b) for b in q] for a in q]) + 1e-12 * np.eye(len(q))
            w = np.linalg.solve(K, [e0(p) for p in self.points])
            return e0(point) - sum(wi * k(unit(point), qi) for wi, qi in zip(w, q))

        def rows(self, point, D):
            calls.append(point)
            err = self.error(point)
            out = []
            for v in self.views:
                m = metrics(point["c1"], point["nu"], target_d=D[v])
                out.append({"view": v, **m, "BS_Av": m["BS_Av"] + err, "TS_Av": m["TS_Av"] + err})
            return out

    monkeypatch.setattr(ev, "SurrogatePipeline", Pipe)
    monkeypatch.setattr(regtrack.case, "load_case", lambda d: d)


def test_surrogate_search_replaces_the_grid_and_full_runs_confirm_it(tmp_path, monkeypatch):
    """With surrogates the grid's 16 full runs and the local optimiser's become one at the
    centre of the box (the fake's D is an output, as with a DICOM thickness) and rounds of
    infill runs at the surrogate's optima (the first with a forward point per parameter):
    the same optimum as the grid calibration (c1 0.8 kPa to 1 %, nu 0.47 to 1e-3, as
    above) from at most a fifth of its full runs (measured: 5 against 51, two rounds),
    every reported score a full run's, and the record says what the surrogate did: its
    optima and their scores, the search settled, uncertainty intervals holding the
    optimum, and the sensitivity taken on the refitted surrogate."""
    calls = []
    _fake_surrogate_pipeline(monkeypatch, calls)
    case = make_case(tmp_path, "A")
    kw = dict(bounds={"c1": (0.2, 3.0), "nu": (0.45, 0.49)}, runner=FAKE, workers=1,
              progress=False, max_evals=40)
    grid = calibrate(case, cache_dir=tmp_path / "cache-grid", **kw)
    res = calibrate(case, cache_dir=tmp_path / "cache-sur",
                    surrogates={"CC": _FakeSurrogate("CC")}, **kw)
    assert res.optimum.params["c1"] == pytest.approx(0.8, rel=0.01)
    assert res.optimum.params["nu"] == pytest.approx(0.47, abs=1e-3)
    assert 5 * res.computed <= grid.computed and len(res.grid) == 1  # measured 5 against 51
    assert not any(r.get("surrogate") for r in res.optimum.rows)  # a full run's rows
    su = res.surrogate
    assert su["evaluations"] == len(calls) > 50 and su["settled"]
    assert 2 <= len(su["rounds"]) <= 4
    assert su["score_error"] == pytest.approx(abs(su["score_surrogate"] - su["score_full"]))
    for n, star in (("c1", 0.8), ("nu", 0.47)):
        lo, hi = su["interval"][n]
        assert lo <= star <= hi and lo <= res.optimum.params[n] <= hi
        assert res.sensitivity[n]["method"] == "central, on the refitted surrogates"
    # the fake's S = const - 10 ln(c1 / 0.8)^2 - 5e4 (nu - 0.47)^2 is flat at its optimum;
    # 10 % above it in c1 the slope is -2.2 per kPa, 0.004 above it in nu -400 per unit
    assert abs(res.sensitivity["c1"]["dS_dparam"]) < 1.0
    assert abs(res.sensitivity["nu"]["dS_dparam"]) < 100.0
    # D from the last full run at the surrogate's optimum (the fake's D depends on c1)
    c1 = su["rounds"][-1]["params"]["c1"]
    assert json.loads(json.dumps(to_json(res)))["surrogate"]["D"] == {"CC": pytest.approx(
        0.45 - 0.1 * math.log(c1 / 0.54), rel=1e-9)}


@pytest.mark.parametrize("bounds, fixed, match", [
    ({"c1": (0.2, 3.0)}, {}, "the surrogate takes c1, nu; calibrate or --fix exactly those"),
    ({"c1": (0.1, 3.0), "nu": (0.45, 0.49)}, {}, r"--c1 0.1 3: outside the CC surrogate's range"),
    ({"c1": (0.2, 3.0), "nu": (0.45, 0.49)}, {"friction": 0.2}, "calibrate or --fix exactly"),
])
def test_a_surrogate_that_does_not_fit_the_calibration_is_refused_before_any_run(
        tmp_path, bounds, fixed, match):
    with pytest.raises(ConfigError, match=match):
        calibrate(make_case(tmp_path, "A"), bounds=bounds, fixed=fixed, runner=FAKE,
                  cache_dir=tmp_path / "c", progress=False, surrogates={"CC": _FakeSurrogate("CC")})
    assert not (tmp_path / "c").exists()
