"""The case report: a PDF of at most six A4 pages a radiologist or researcher can read.

Pages (:func:`render_pages`):

1. the case, its mode, the verdict (fit-quality checks with their thresholds,
   :mod:`regtrack.report.verdict`), the metrics of every view (the quantities of Tables
   3-4 of Lapuebla-Ferri et al.) with units, and the overlays of every view after the
   rotation theta_p;
2. one page per view: the compression sequence (the breast between the plates after each
   step), the simulation steps, the contours before and after the rotation with their
   centroids (Figure 9 of the paper), and the real beside the virtual image on the same
   axes;
3. the extra pages the pipeline adds (lesion tracking; the biopsy target,
   :mod:`regtrack.report.biopsy`, which has no views and so no summary page);
4. an appendix: the truth-vs-result table when the case has a ground truth, the model,
   the settings that differ from the defaults, and provenance (versions, inputs by hash).

The full configuration and every figure's numbers are in the JSON files beside the PDF;
the PDF prints no raw JSON.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack import __version__, _io
from regtrack.report import pages as P
from regtrack.report.fmt import num
from regtrack.report.verdict import Check, check_view, verdict_line

#: (key in the metrics row, column title, decimals)
METRIC_COLUMNS = (
    ("view", "View", None),
    ("BS_Av", "BS_Av (%)", 1),
    ("TS_Av", "TS_Av (%)", 1),
    ("theta_p_b", "θp,b (°)", 2),
    ("theta_p_t", "θp,t (°)", 2),
    ("theta_p", "θp (°)", 2),
    ("D", "D (%)", 1),
    ("d_T", "d_T (mm)", 2),
    ("d_B", "d_B (mm)", 2),
    ("force_N", "Force (N)", 1),
)

EXPLANATION = (
    "BS_Av, TS_Av: breast and tumour similarity, the share of the summed closest-point "
    "distance (virtual to real contour) left by the nipple superposition that the rotation "
    "θp removes (eqs. 4-5). θp,b, θp,t: optimal in-plane rotations of the breast and the "
    "tumour (golden-section search); θp is their mean. D: compression degree, the relative "
    "reduction of the breast thickness between the plates. d_T, d_B: distances between the "
    "centroids of the real and virtual tumour and breast after alignment. Force: on the "
    "upper plate at the end of the compression."
)


@dataclass
class Sequence:
    """What the compression-sequence panels need: the reference mesh (model frame, mm),
    the step records and each step's displacement."""

    points: np.ndarray
    skin: np.ndarray
    steps: list[dict]
    states: list[np.ndarray]
    plate_frame: dict
    cut: np.ndarray | None = None  # outer faces cut by the MRI's field of view


@dataclass
class ViewReport:
    """What the report shows of one view."""

    view: str
    metrics: dict
    real: Any = None  # MammogramView
    virtual: Any = None  # MammogramView
    alignment: Any = None  # Alignment
    steps: list[dict] = field(default_factory=list)  # rows of the steps table
    pictures: list[Path] = field(default_factory=list)  # sequence PNG (without ``sequence``)
    simulation: dict = field(default_factory=dict)  # {"summary", "steps"} of the result JSON
    sequence: Sequence | None = None


#: an appendix table: (heading, column titles, rows, column x positions, wrap widths)
AppendixTable = tuple[str, list[str], list[list[str]], list[float], list[int]]


@dataclass
class CaseReport:
    """Everything the PDF shows.  ``header``: lines under the title (the mode, the
    model); ``appendix``: the appendix tables in order (the pipeline adds truth, model,
    settings and provenance; a caller may add more)."""

    case_id: str
    title: str = ""
    views: list[ViewReport] = field(default_factory=list)
    header: list[str] = field(default_factory=list)
    appendix: list[AppendixTable] = field(default_factory=list)
    #: callables drawing extra A4 pages (e.g. the lesion-tracking section) on a Figure
    extra_pages: list[Callable] = field(default_factory=list)


def metrics_table(rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Column titles and formatted cells of the metrics table (D shown in %)."""
    head = [t for _, t, _ in METRIC_COLUMNS]
    cells = []
    for r in rows:
        r = dict(r)
        if r.get("D") is not None:
            r["D"] = 100.0 * r["D"]
        cells.append([str(r.get(k, "–")) if d is None else num(r.get(k), d)
                      for k, _, d in METRIC_COLUMNS])
    return head, cells


def case_checks(report: CaseReport) -> list[Check]:
    """The verdict's checks of every view with a registration."""
    checks: list[Check] = []
    for v in report.views:
        if v.real is None:
            continue
        nipple = (getattr(v.real, "meta", None) or {}).get("nipple")
        checks += check_view(v.view, v.metrics, simulation=v.simulation, nipple=nipple)
    return checks


def render_pages(report: CaseReport) -> Iterator[Any]:
    """Yield each page of the report as an A4 matplotlib figure (closed by the caller).

    A report without views and with extra pages (the 3-D tracking of ``regtrack track
    --view biopsy``, :mod:`regtrack.report.biopsy`) has no summary page: it starts with
    its own pages."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if report.views or not report.extra_pages:
        checks = case_checks(report)
        header = [*report.header, f"regtrack {__version__} · {_dt.date.today().isoformat()}"]
        fig = plt.figure(figsize=P.A4)
        head, rows = metrics_table([v.metrics for v in report.views])
        P.summary_page(fig, report, checks, verdict_line(checks), head, rows, EXPLANATION,
                       header)
        yield fig
    for v in report.views:
        fig = plt.figure(figsize=P.A4)
        P.view_page(fig, v)
        yield fig
    for draw in report.extra_pages:
        fig = plt.figure(figsize=P.A4)
        draw(fig)
        yield fig
    if report.appendix:
        fig = plt.figure(figsize=P.A4)
        P.appendix_page(fig, report.appendix)
        yield fig


def figure_text(fig) -> list[str]:
    """Every text string drawn on ``fig`` (titles, labels, table cells, legends)."""
    from matplotlib.table import Table
    from matplotlib.text import Text

    texts = [t.get_text() for t in fig.findobj(Text)]
    for table in fig.findobj(Table):
        texts += [c.get_text().get_text() for c in table.get_celld().values()]
    return [t for t in texts if t]


def write_pdf(report: CaseReport, path: str | Path) -> Path:
    """Write the report PDF atomically; return its path."""
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    with _io.atomic_path(path) as tmp, PdfPages(tmp) as pdf:
        for fig in render_pages(report):
            try:
                pdf.savefig(fig)
            finally:
                plt.close(fig)
    return Path(path)
