"""Long fuzz run of the input-facing code (issue 10): >= 10,000 inputs per target.

Usage::

    .venv/bin/python pipelines/fuzz.py [--examples 10000] [--jobs 4] [--only registration ...]
        [--seed 1] [--json fuzz.json]

The targets and the property are those of ``tests/test_fuzz.py`` (CI runs the same
targets with 200 examples each): every input either succeeds with sane output or raises
a :class:`regtrack.errors.RegtrackError`.  One process per target (``--jobs`` at a time);
each prints how many inputs it ran, how many were accepted / rejected with a domain
error, its wall time, and the falsifying example of a crash.  Exit status 1 when any
target crashed.  Hypothesis shrinks a crash to a minimal input: pin it as a regression
test in ``tests/test_fuzz.py``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import traceback
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def _run_one(name: str, examples: int, seed: int) -> dict:
    """Run one target in this process; return its figures."""
    warnings.simplefilter("ignore")  # pydicom warns on every malformed value
    logging.disable(logging.CRITICAL)  # the readers log each fall-back they take
    from regtrack.errors import RegtrackError
    from tests import test_fuzz as F

    target = F.TARGETS[name]
    outcome = {"accepted": 0, "domain_error": 0}
    check = target.check

    def counting(example):
        try:
            check(example)
        except RegtrackError:  # pragma: no cover - checks swallow these themselves
            outcome["domain_error"] += 1
            raise
        outcome["accepted"] += 1

    # count domain errors through expect_domain_error
    original = F.expect_domain_error

    def expect(fn):
        try:
            return fn()
        except RegtrackError:
            outcome["domain_error"] += 1
            return None

    F.expect_domain_error = expect
    t0 = time.perf_counter()
    crash = None
    try:
        n = F.run_target(F.Target(name, target.strategy, counting), max_examples=examples,
                         rng_seed=seed)
    except BaseException as err:  # noqa: BLE001 - report every crash
        n = outcome["accepted"]
        crash = "".join(traceback.format_exception(err))[-4000:]
    finally:
        F.expect_domain_error = original
    return {"target": name, "inputs": n, "checks_passed": outcome["accepted"],
            "domain_errors": outcome["domain_error"], "seconds": round(time.perf_counter() - t0, 1),
            "crash": crash}


def main(argv: list[str] | None = None) -> int:
    from tests.test_fuzz import TARGETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=10_000, help="inputs per target")
    ap.add_argument("--jobs", type=int, default=2, help="targets run in parallel")
    ap.add_argument("--only", nargs="*", default=None, choices=sorted(TARGETS))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    names = args.only or sorted(TARGETS)
    rows = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = {pool.submit(_run_one, n, args.examples, args.seed): n for n in names}
        for fut in as_completed(futs):
            r = fut.result()
            rows.append(r)
            status = "CRASH" if r["crash"] else "ok"
            print(f"{r['target']:<16} {r['inputs']:>7} inputs  {r['domain_errors']:>7} domain "
                  f"errors  {r['seconds']:>7.1f} s  {status}", flush=True)
            if r["crash"]:
                print(r["crash"], flush=True)
    rows.sort(key=lambda r: r["target"])
    print("\ntarget            inputs  domain-errors  seconds  crashes")
    for r in rows:
        print(f"{r['target']:<16} {r['inputs']:>7}  {r['domain_errors']:>13}  "
              f"{r['seconds']:>7.1f}  {1 if r['crash'] else 0}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 1 if any(r["crash"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
