"""The case report: a PDF a radiologist or researcher can read, plus the tables.

Pages: (1) case summary and the metrics of every view (the quantities of Tables 3-4 of
Lapuebla-Ferri et al.); (2) the model; (3) per view, the compression sequence and the
simulation steps; (4) per view, real and virtual contours before and after the rotation
with centroids (Figure 9) and the real image beside the X-ray-like virtual image;
(5) parameters and provenance.
"""

from __future__ import annotations

import datetime as _dt
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from regtrack import __version__, _io
from regtrack.report import figures as F

#: (key in the metrics row, column title, format)
METRIC_COLUMNS = (
    ("view", "view", "{}"),
    ("BS_Av", "BS_Av (%)", "{:.1f}"),
    ("TS_Av", "TS_Av (%)", "{:.1f}"),
    ("theta_p_b", "θp,b (°)", "{:.2f}"),
    ("theta_p_t", "θp,t (°)", "{:.2f}"),
    ("theta_p", "θp (°)", "{:.2f}"),
    ("D", "D (%)", "{:.1f}"),
    ("d_T", "d_T (mm)", "{:.2f}"),
    ("d_B", "d_B (mm)", "{:.2f}"),
    ("force_N", "F (N)", "{:.1f}"),
)

EXPLANATION = (
    "BS_Av, TS_Av: breast and tumour similarity (%) = (1 - Σ‖d‖ at θp / Σ‖d‖ at θ=0)·100, "
    "closest-point distances from the virtual to the real contour (eqs. 4-5). "
    "θp,b, θp,t: optimal in-plane rotations (golden-section search) for the breast and the "
    "tumour; θp is their mean. D: compression degree, relative reduction of the mean breast "
    "thickness between the plates. d_T, d_B: distances between the centroids of the real and "
    "virtual tumour and breast contours after alignment. F: upper-plate force."
)


@dataclass
class ViewReport:
    """What the report shows of one view."""

    view: str
    metrics: dict
    real: object = None  # MammogramView
    virtual: object = None  # MammogramView
    alignment: object = None  # Alignment
    steps: list[dict] = field(default_factory=list)  # per simulation step
    pictures: list[Path] = field(default_factory=list)  # compression-sequence PNGs


@dataclass
class CaseReport:
    case_id: str
    title: str = ""
    views: list[ViewReport] = field(default_factory=list)
    model_summary: dict = field(default_factory=dict)
    model_pictures: list[Path] = field(default_factory=list)
    config: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    #: callables drawing extra A4 pages (e.g. the lesion-tracking section) on a Figure
    extra_pages: list = field(default_factory=list)
    #: lines under the metrics table: the mode that ran, the lesion predictions, and where
    #: each geometry value (plate gap, force, angle, projection) came from
    notes: list[str] = field(default_factory=list)


def _fmt(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    try:
        return fmt.format(value)
    except (ValueError, TypeError):
        return str(value)


def metrics_table(rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Column titles and formatted cells of the metrics table (D shown in %)."""
    head = [t for _, t, _ in METRIC_COLUMNS]
    cells = []
    for r in rows:
        r = dict(r)
        if r.get("D") is not None:
            r["D"] = 100.0 * r["D"]
        cells.append([_fmt(r.get(k), f) for k, _, f in METRIC_COLUMNS])
    return head, cells


def _text_page(pdf, title: str, lines: list[str], *, plt) -> None:
    per_page = 62
    for start in range(0, max(len(lines), 1), per_page):
        fig = plt.figure(figsize=(8.27, 11.69))
        fig.text(0.06, 0.96, title + (" (cont.)" if start else ""), fontsize=13, weight="bold")
        fig.text(0.06, 0.93, "\n".join(lines[start:start + per_page]), fontsize=7,
                 family="monospace", va="top")
        pdf.savefig(fig)
        plt.close(fig)


def _table(ax, head, cells, *, fontsize=8):
    ax.axis("off")
    if not cells:
        ax.text(0.5, 0.5, "no rows", ha="center")
        return
    t = ax.table(cellText=cells, colLabels=head, loc="upper center", cellLoc="center")
    t.auto_set_font_size(False)
    t.set_fontsize(fontsize)
    t.scale(1, 1.4)


def _image_page(pdf, title: str, paths: list[Path], *, plt) -> None:
    paths = [p for p in paths if Path(p).is_file()]
    if not paths:
        return
    n = len(paths)
    fig, axes = plt.subplots(n, 1, figsize=(8.27, 11.69))
    axes = np.atleast_1d(axes)
    for ax, p in zip(axes, paths):
        ax.imshow(plt.imread(str(p)))
        ax.axis("off")
    fig.suptitle(title, fontsize=13, weight="bold")
    pdf.savefig(fig)
    plt.close(fig)


def write_pdf(report: CaseReport, path: str | Path) -> Path:
    """Write the report PDF atomically; return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    with _io.atomic_path(path) as tmp, PdfPages(tmp) as pdf:
        # 1. summary
        fig = plt.figure(figsize=(8.27, 11.69))
        fig.text(0.06, 0.95, f"regtrack report: case {report.case_id}", fontsize=16, weight="bold")
        fig.text(0.06, 0.925, report.title, fontsize=10)
        fig.text(0.06, 0.905, f"regtrack {__version__} · {_dt.date.today().isoformat()}", fontsize=8,
                 color="0.4")
        ax = fig.add_axes([0.04, 0.62, 0.92, 0.25])
        head, cells = metrics_table([v.metrics for v in report.views])
        _table(ax, head, cells)
        fig.text(0.06, 0.58, "\n".join(textwrap.wrap(EXPLANATION, 110)), fontsize=8, va="top")
        wrapped = [w for line in report.notes for w in textwrap.wrap(line, 120) or [""]][:24]
        if wrapped:
            fig.text(0.06, 0.50, "\n".join(wrapped), fontsize=6.5, va="top", family="monospace")
        ms = report.model_summary
        if ms:
            lines = [f"{k}: {v}" for k, v in ms.items()]
            top = 0.48 - 0.0115 * len(wrapped) if wrapped else 0.45
            fig.text(0.06, top, "Model\n" + "\n".join(lines[:20]), fontsize=8, va="top",
                     family="monospace")
        pdf.savefig(fig)
        plt.close(fig)
        # 2. model
        _image_page(pdf, "Patient model", list(report.model_pictures)[:2], plt=plt)
        # 3-4. views
        for v in report.views:
            _image_page(pdf, f"{v.view}: compression sequence", list(v.pictures)[:2], plt=plt)
            if v.steps:
                fig = plt.figure(figsize=(8.27, 11.69))
                fig.text(0.06, 0.95, f"{v.view}: simulation steps", fontsize=13, weight="bold")
                keys = [k for k in ("step", "D", "force_N", "max_penetration_mm", "behind_wall_mm",
                                    "increments", "iterations", "seconds")
                        if any(k in s for s in v.steps)]
                cells = [[_fmt(s.get(k), "{:.4g}" if k != "step" else "{}") for k in keys] for s in v.steps]
                _table(fig.add_axes([0.04, 0.5, 0.92, 0.4]), keys, cells)
                pdf.savefig(fig)
                plt.close(fig)
            if v.real is None and v.virtual is not None:
                fig = F.virtual_figure(v.virtual)
                fig.suptitle(f"{v.view}: virtual mammogram (no real mammogram in the case)",
                             fontsize=11)
                pdf.savefig(fig)
                plt.close(fig)
            if v.real is not None and v.virtual is not None and v.alignment is not None:
                fig = plt.figure(figsize=(8.27, 11.69))
                axes = [fig.add_axes([0.07, 0.56, 0.4, 0.36]), fig.add_axes([0.55, 0.56, 0.4, 0.36])]
                F.draw_overlay(axes[0], v.real, v.virtual, v.alignment, theta_deg=0.0,
                               title=f"{v.view}: at the nipple (θ = 0°)")
                F.draw_overlay(axes[1], v.real, v.virtual, v.alignment, theta_deg=v.alignment.theta_p,
                               title=f"{v.view}: θp = {v.alignment.theta_p:.2f}°")
                for k, (img_v, name) in enumerate(((v.real, "real"), (v.virtual, "virtual"))):
                    ax = fig.add_axes([0.07 + 0.48 * k, 0.08, 0.4, 0.4])
                    if img_v.image is not None:
                        ax.imshow(img_v.image, cmap="gray", extent=F.image_extent(img_v), vmin=0, vmax=1)
                    ax.plot(*img_v.breast_contour.T, color=F.REAL if k == 0 else F.VIRTUAL, lw=1)
                    ax.set_title(f"{name} {v.view}", fontsize=10)
                    ax.set_aspect("equal")
                    ax.set_xlabel("x (mm)")
                pdf.savefig(fig)
                plt.close(fig)
        for draw in report.extra_pages:
            fig = plt.figure(figsize=(8.27, 11.69))
            draw(fig)
            pdf.savefig(fig)
            plt.close(fig)
        # 5. provenance
        lines = []
        for title, obj in (("configuration", report.config), ("provenance", report.provenance)):
            lines.append(f"[{title}]")
            lines += _io.to_json(obj, indent=1).splitlines()
            lines.append("")
        wrapped = [w for ln in lines for w in (textwrap.wrap(ln, 120, subsequent_indent="    ") or [""])]
        _text_page(pdf, "Parameters and provenance", wrapped, plt=plt)
    return Path(path)
