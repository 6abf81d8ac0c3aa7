"""Benchmark of the study engine: speed-up from 1 to 2 local workers and cache hit rates.

    python pipelines/run_study_benchmark.py [--runner fake]
        [--case sample_cases/phantom01] [--c1 0.4 0.8 1.6] [--nu 0.47]

Runs the same study (one case by default; c1 x nu grid, coarse mesh) three times in one
process, each in a fresh cache except where stated:

1. 1 local worker, cold cache;
2. 2 local workers, cold cache  -> speed-up = t1 / t2;
3. 2 local workers, the cache of run 2 plus one more nu value -> only the new runs run
   (hit rate = cached / total);
4. the same again -> hit rate 100 %, no run computed.

The default runner is the real pipeline; with the fake runner (``--runner fake``,
registered by tests/_study_fakes.py,
``sleep`` seconds per run, no CPU work) the speed-up measures the engine's overhead only.
The machine's other load makes times noisy: compare the ratios of one invocation.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _study_file(folder: Path, *, case: Path, c1: list[float], nu: list[float], runner: str,
                workers: int, nodes: int) -> Path:
    p = folder / f"bench_{workers}.toml"
    p.write_text(f"""
[study]
name = "bench"
views = ["CC"]
outputs = ["csv"]
runner = "{runner}"
workers = {workers}
[cases]
paths = ["{case}"]
[parameters]
c1 = {json.dumps(c1)}
nu = {json.dumps(nu)}
[overrides.model]
target_nodes = {nodes}
""")
    return p


def _run(study_file: Path, out: Path) -> dict:
    from regtrack.study.run import run_study
    from regtrack.study.spec import load_study

    t0 = time.perf_counter()
    res = run_study(load_study(study_file, out=out), progress=False)
    ex = res.execution
    return {"seconds": time.perf_counter() - t0, "runs": len(res.runs),
            "computed": len(ex.computed), "cached": len(ex.cached), "failed": res.n_failed,
            "hit_rate": ex.hit_rate, "workers": ex.workers}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runner", default="pipeline", help="registered runner name ('fake' "
                    "registers the test stand-in of tests/_study_fakes.py)")
    ap.add_argument("--case", type=Path, default=REPO / "sample_cases" / "phantom01")
    ap.add_argument("--c1", nargs="+", type=float, default=[0.4, 0.8, 1.6])
    ap.add_argument("--nu", nargs="+", type=float, default=[0.47])
    ap.add_argument("--extra-nu", type=float, default=0.49)
    ap.add_argument("--nodes", type=int, default=3000)
    args = ap.parse_args()
    if args.runner == "fake":
        sys.path.insert(0, str(REPO))
        import tests._study_fakes  # noqa: F401 - registers the "fake" runner
    tmp = Path(tempfile.mkdtemp(prefix="regtrack-bench-"))
    try:
        case = args.case.resolve()
        kw = dict(case=case, c1=args.c1, runner=args.runner, nodes=args.nodes)
        rows = []
        r1 = _run(_study_file(tmp, nu=args.nu, workers=1, **kw), tmp / "w1")
        rows.append(("1 worker, cold cache", r1))
        r2 = _run(_study_file(tmp, nu=args.nu, workers=2, **kw), tmp / "w2")
        rows.append(("2 workers, cold cache", r2))
        more = _study_file(tmp, nu=args.nu + [args.extra_nu], workers=2, **kw)
        rows.append(("2 workers, +1 nu value", _run(more, tmp / "w2")))
        rows.append(("2 workers, re-run", _run(more, tmp / "w2")))
        print(f"{'study':28s} {'runs':>5s} {'computed':>9s} {'cached':>7s} {'failed':>7s} "
              f"{'hit rate':>9s} {'time s':>8s}")
        for name, r in rows:
            print(f"{name:28s} {r['runs']:5d} {r['computed']:9d} {r['cached']:7d} {r['failed']:7d} "
                  f"{100 * r['hit_rate']:8.0f}% {r['seconds']:8.2f}")
        print(f"speed-up 1 -> 2 workers: {r1['seconds'] / r2['seconds']:.2f}x "
              f"(runner {args.runner}, case {case.name})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
