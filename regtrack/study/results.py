"""Per-run result cache and the study's tidy table.

**Cache.**  Each finished run is one JSON file ``<cache>/study-runs/<run_key>.json``
written atomically (:mod:`regtrack._io`), so a study killed at any moment resumes with
every run that finished.  Successful runs and *deterministic* failures (a
:class:`regtrack.errors.RegtrackError`: bad input, mesh or convergence failure, which the
same inputs would raise again) are kept; other failures (a worker that died, an
unexpected exception) are not, so the next study run attempts them again.

**Table.**  One row per case x parameter point x view, sorted in study order, with the
columns ``case_id, view, status, error, <parameters...>, <metrics...>, run_key``.  Failed
runs keep their rows (status ``failed``, the error, empty metrics) so the table stays
rectangular and the failures are visible.  CSV always; Parquet only when ``pyarrow`` is
installed (it is an optional extra: ~100 MB for a second copy of the same table, so it is
not a core dependency).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from regtrack import _io
from regtrack.study.runner import FAILED, OK, RunSpec

log = logging.getLogger(__name__)

LEAD_COLUMNS = ("case_id", "view", "status", "error")


@dataclass
class ResultCache:
    """Run outcomes under ``root`` keyed by run key; hits and misses are counted."""

    root: Path
    hits: int = 0
    misses: int = 0

    def __post_init__(self) -> None:
        from regtrack.pipeline.cache import remove_stale_parts

        self.root = Path(self.root)
        remove_stale_parts(self.root)  # atomic writes of a killed study

    def path(self, key: str) -> Path:
        return self.root / f"{key}.json"

    def load(self, key: str, *, retry_failed: bool = False) -> dict | None:
        """The cached outcome of ``key``, or None when the run must be computed."""
        p = self.path(key)
        try:
            outcome = json.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            outcome = None
        except (OSError, json.JSONDecodeError) as exc:  # cannot happen with atomic writes
            log.warning("ignoring unreadable cached run %s (%s); it will be recomputed", p, exc)
            outcome = None
        if outcome is not None and outcome.get("status") == FAILED and retry_failed:
            outcome = None
        if outcome is None:
            self.misses += 1
            return None
        self.hits += 1
        return outcome

    def store(self, outcome: dict) -> bool:
        """Keep ``outcome`` if it is worth re-using; return whether it was stored."""
        if outcome["status"] == FAILED and not outcome.get("deterministic"):
            return False
        _io.write_json(self.path(outcome["run_key"]), outcome)
        return True

    def keys(self) -> set[str]:
        return {p.stem for p in self.root.glob("*.json")} if self.root.is_dir() else set()

    @property
    def hit_rate(self) -> float:
        n = self.hits + self.misses
        return self.hits / n if n else 0.0


def table_rows(runs: list[RunSpec], outcomes: dict[str, dict]) -> list[dict]:
    """Tidy rows (study order) from the runs and their outcomes (keyed by run key)."""
    rows: list[dict] = []
    for spec in sorted(runs, key=lambda r: r.index):
        out = outcomes.get(spec.run_key)
        status = out["status"] if out else "missing"
        error = out.get("error") if out else "not run (study interrupted)"
        by_view = {r.get("view"): r for r in (out or {}).get("rows", [])}
        for view in spec.views:
            metrics = {k: v for k, v in by_view.get(view, {}).items()
                       if k not in ("case_id", "view")}
            rows.append({"case_id": spec.case_id, "view": view, "status": status,
                         "error": error if status != OK else None, **spec.params, **metrics,
                         "run_key": spec.run_key})
    return rows


def columns(rows: list[dict], param_names: list[str]) -> list[str]:
    """Column order: lead columns, parameters, metrics (first-seen order), run key."""
    cols = list(LEAD_COLUMNS) + list(param_names)
    for r in rows:
        cols += [k for k in r if k not in cols and k != "run_key"]
    return cols + ["run_key"]


def _cell(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return repr(v)  # shortest round-trip form: identical text for identical floats
    return str(v)


def to_csv_text(rows: list[dict], cols: list[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in cols])
    return buf.getvalue()


def read_csv(path: str | Path) -> list[dict]:
    """Rows of a study table; numeric cells become float, empty cells None."""
    out = []
    with open(path, newline="", encoding="utf-8") as fh:
        for r in csv.DictReader(fh):
            row: dict[str, Any] = {}
            for k, v in r.items():
                if v == "":
                    row[k] = None
                    continue
                try:
                    row[k] = float(v)
                except ValueError:
                    row[k] = v
            out.append(row)
    return out


def write_table(rows: list[dict], cols: list[str], out_dir: Path, *,
                parquet: bool) -> list[Path]:
    """Write ``table.csv`` (and ``table.parquet`` when asked and pyarrow is present)."""
    written = [_io.write_text(out_dir / "table.csv", to_csv_text(rows, cols))]
    if parquet:
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            log.warning("table.parquet not written: pyarrow is not installed "
                        "(pip install pyarrow); table.csv holds the same data")
            return written
        data = {c: [r.get(c) for r in rows] for c in cols}
        with _io.atomic_path(out_dir / "table.parquet") as tmp:
            pq.write_table(pa.table(data), tmp)
        written.append(out_dir / "table.parquet")
    return written


def failures(runs: list[RunSpec], outcomes: dict[str, dict]) -> list[dict]:
    """One record per failed run: case, parameters, error type and message."""
    out = []
    for spec in sorted(runs, key=lambda r: r.index):
        o = outcomes.get(spec.run_key)
        if o and o["status"] == FAILED:
            out.append({"case_id": spec.case_id, "params": spec.params, "run_key": spec.run_key,
                        "error_type": o.get("error_type"), "error": o.get("error")})
    return out
