"""``regtrack study STUDY.toml``: run a parametric study / cohort, locally or on Dask."""

from __future__ import annotations

import argparse
import logging

HELP = "run a parametric study or cohort (study TOML), locally or on a Dask cluster"

log = logging.getLogger("regtrack.study")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("study", help="study TOML (see pipelines/example_study.toml)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="Dask scheduler address (tcp://host:8786); default: local pool")
    parser.add_argument("--workers", type=int, default=None,
                        help="local worker processes (default [study] workers; 0 = machine)")
    parser.add_argument("--out", help="output folder (default [study] out)")
    parser.add_argument("--cache", help="cache folder (default <out>/cache)")
    parser.add_argument("--runner", help="name of a registered runner (default: pipeline; "
                        "packages add runners through the 'regtrack.study_runners' entry "
                        "points)")
    parser.add_argument("--retry-failed", action="store_true",
                        help="recompute runs whose failure is cached (e.g. after fixing a case)")
    parser.add_argument("--dry-run", action="store_true", help="validate, list the runs, and stop")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Exit 0 when every run succeeded, 4 when the study finished with failed runs."""
    from regtrack.cli._checks import writable_folder
    from regtrack.study.runner import make_runs
    from regtrack.study.spec import load_study

    writable_folder(args.out, "--out")
    writable_folder(args.cache, "--cache")

    study = load_study(args.study, out=args.out, cache=args.cache, workers=args.workers,
                       runner=args.runner)
    for w in study.warnings:
        log.warning("%s", w)
    writable_folder(study.out_dir, "[study] out")
    writable_folder(study.cache_dir, "[study] cache")
    if args.dry_run:
        runs = make_runs(study)
        log.info("study %s: %d cases x %d parameter points = %d runs, views %s", study.name,
                 len(study.cases), len(study.points()), len(runs), ",".join(study.views))
        for r in runs:
            log.info("  %s %s %s", r.run_key, r.case_id, r.params)
        return 0
    from regtrack.study.run import run_study

    result = run_study(study, scheduler=args.scheduler, retry_failed=args.retry_failed,
                       progress=not args.no_progress)
    ex = result.execution
    log.info("study %s: %d runs, %d ok, %d failed; computed %d, cached %d (hit rate %.0f %%), "
             "%.1f s on %s (%d workers)", study.name, len(result.runs),
             len(result.runs) - result.n_failed, result.n_failed, len(ex.computed),
             len(ex.cached), 100 * ex.hit_rate, ex.seconds, ex.backend, ex.workers)
    for f in result.failures:
        log.warning("failed: %s %s: %s: %s", f["case_id"], f["params"], f["error_type"], f["error"])
    log.info("results in %s", study.out_dir)
    return 4 if result.n_failed else 0
