"""Run a whole study: execute its runs and write the table, summary, plots and PDF.

Output folder (``[study] out``)::

    table.csv           one row per case x parameters x view, every metric
    table.parquet       the same, when pyarrow is installed and "parquet" is asked for
    summary.json        counts, failures with reasons, cache hit rate, timing, the study
    study.toml          the study file that was run (reproducibility)
    figure8_<case>_<view>.png, d_T.png, study.pdf
    cache/              stage cache (meshes, simulations) + study-runs/ (per-run results)
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from regtrack import __version__, _io
from regtrack.study.engine import Engine, Execution
from regtrack.study.results import columns, failures, table_rows, write_table
from regtrack.study.runner import RunSpec, make_runs
from regtrack.study.spec import Study

log = logging.getLogger(__name__)


@dataclass
class StudyResult:
    """A finished study: its runs, what the engine did, the table and the files written."""

    study: Study
    runs: list[RunSpec]
    execution: Execution
    rows: list[dict]
    columns: list[str]
    failures: list[dict]
    files: list[Path] = field(default_factory=list)

    @property
    def n_failed(self) -> int:
        return len(self.failures)


def summary(result: StudyResult) -> dict:
    """The JSON summary of a study (counts, failures, hit rate, timing)."""
    ex = result.execution
    st = result.study
    return {
        "study": st.name, "study_file": str(st.path), "regtrack_version": __version__,
        "runner": st.runner, "cases": [c.case_id for c in st.cases],
        "parameters": {k: list(v) for k, v in st.parameters.items()},
        "views": list(st.views), "overrides": st.overrides,
        "runs": len(result.runs), "rows": len(result.rows),
        "ok": len(result.runs) - len(result.failures), "failed": len(result.failures),
        "cached": len(ex.cached), "computed": len(ex.computed), "retried": ex.retried,
        "cache_hit_rate": ex.hit_rate, "seconds": ex.seconds, "backend": ex.backend,
        "workers": ex.workers, "failures": result.failures,
        "run_seconds": {k: o.get("seconds") for k, o in ex.outcomes.items()
                        if k in set(ex.computed)},
    }


def run_study(study: Study, *, scheduler: str | None = None, retry_failed: bool = False,
              progress: bool = True) -> StudyResult:
    """Execute ``study`` (locally, or on the Dask cluster at ``scheduler``) and write outputs.

    Failing runs are recorded (table rows with status ``failed``, ``summary.json``
    failures); they do not stop the study.
    """
    runs = make_runs(study)
    study.out_dir.mkdir(parents=True, exist_ok=True)
    _io.write_text(study.out_dir / "study.toml", study.path.read_text(encoding="utf-8"))
    with Engine(runner=study.runner, cache_dir=study.cache_dir, scheduler=scheduler,
                workers=study.workers, memory_per_run_gb=study.memory_per_run_gb,
                retries=study.retries, retry_failed=retry_failed, progress=progress) as engine:
        ex = engine.run(runs, label=study.name)
    rows = table_rows(runs, ex.outcomes)
    cols = columns(rows, list(study.parameters))
    result = StudyResult(study=study, runs=runs, execution=ex, rows=rows, columns=cols,
                         failures=failures(runs, ex.outcomes))
    write_outputs(result)
    return result


def write_outputs(result: StudyResult) -> list[Path]:
    """Write the table(s), summary and requested figures/PDF; return the paths."""
    st = result.study
    files: list[Path] = []
    if "csv" in st.outputs or "parquet" in st.outputs:
        files += write_table(result.rows, result.columns, st.out_dir,
                             parquet="parquet" in st.outputs)
    info = summary(result)
    files.append(_io.write_json(st.out_dir / "summary.json", info))
    if {"figure8", "d_T", "pdf"} & set(st.outputs):
        from regtrack.study import plots

        files += plots.write_study_figures(result, info)
    result.files = files
    return files
