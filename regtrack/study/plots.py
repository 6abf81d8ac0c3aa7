"""Study figures: the paper's Figure 8, d_T against the parameters, and the study PDF.

Figure 8 of Lapuebla-Ferri et al. plots the registration indicators BS_Av and TS_Av (%)
and the compression degree D against the tissue's neo-Hookean c1 (kPa), one curve per
Poisson's ratio nu.  :func:`figure8` draws it for one case and view (and one value of
every other varied parameter).  Figures are built with :class:`matplotlib.figure.Figure`
(no pyplot state, safe in worker threads) and written atomically.
"""

from __future__ import annotations

import logging
import math
import textwrap
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from regtrack import _io
from regtrack.study.runner import OK

log = logging.getLogger(__name__)

FIG8_METRICS = (("BS_Av", "BS_Av (%)"), ("TS_Av", "TS_Av (%)"), ("D", "D (-)"))


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


def fig8_groups(rows: list[dict], param_names: list[str]) -> dict[tuple, list[dict]]:
    """Successful rows grouped by (case, view, other parameters); c1 and nu excluded."""
    others = [p for p in param_names if p not in ("c1", "nu")]
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        if r.get("status") == OK:
            groups[(r["case_id"], r["view"], tuple((p, r.get(p)) for p in others))].append(r)
    return dict(groups)


def figure8(rows: list[dict], *, title: str) -> Figure:
    """BS_Av, TS_Av and D against c1 (kPa), one curve per nu, for rows of one case/view."""
    fig = Figure(figsize=(11, 3.6), layout="constrained")
    axes = fig.subplots(1, 3)
    by_nu: dict[Any, list[dict]] = defaultdict(list)
    for r in rows:
        by_nu[r.get("nu")].append(r)
    for ax, (key, label) in zip(axes, FIG8_METRICS):
        for nu in sorted(by_nu, key=lambda v: (v is None, v)):
            rs = sorted(by_nu[nu], key=lambda r: r["c1"])
            c1 = np.array([_num(r["c1"]) for r in rs])
            y = np.array([_num(r.get(key)) for r in rs])
            ax.plot(c1, y, marker="o", ms=4, label=f"nu = {nu}" if nu is not None else "nu (case)")
        ax.set_xlabel("c1 (kPa)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    return fig


def dt_figure(rows: list[dict], param_names: list[str], *, title: str) -> Figure:
    """d_T (mm) against each varied parameter; one series per case and view (mean +- range)."""
    names = [p for p in param_names if any(_num(r.get(p)) == _num(r.get(p)) for r in rows)] or ["run"]
    fig = Figure(figsize=(4.2 * len(names), 3.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(names)))
    ok = [r for r in rows if r.get("status") == OK]
    series = sorted({(r["case_id"], r["view"]) for r in ok})
    for ax, name in zip(axes, names):
        for case_id, view in series:
            rs = [r for r in ok if (r["case_id"], r["view"]) == (case_id, view)]
            xs = sorted({_num(r.get(name)) for r in rs}) if name != "run" else []
            if name == "run":
                ax.plot(range(len(rs)), [_num(r.get("d_T")) for r in rs], "o", label=f"{case_id} {view}")
                continue
            ys = [[_num(r.get("d_T")) for r in rs if _num(r.get(name)) == x] for x in xs]
            mean = [np.nanmean(y) if np.isfinite(y).any() else np.nan for y in map(np.array, ys)]
            lo = [np.nanmin(y) if np.isfinite(y).any() else np.nan for y in map(np.array, ys)]
            hi = [np.nanmax(y) if np.isfinite(y).any() else np.nan for y in map(np.array, ys)]
            line, = ax.plot(xs, mean, marker="o", ms=4, label=f"{case_id} {view}")
            ax.fill_between(xs, lo, hi, color=line.get_color(), alpha=0.15)
        ax.set_xlabel(name)
        ax.set_ylabel("d_T (mm)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    return fig


def summary_page(summary: dict) -> Figure:
    """A text page: the study, counts, cache hit rate, timing and failures with reasons."""
    fig = Figure(figsize=(8.27, 11.69))
    lines = [f"Study: {summary['study']}   (regtrack {summary['regtrack_version']})",
             f"File: {summary['study_file']}",
             f"Cases ({len(summary['cases'])}): {', '.join(summary['cases'])}",
             f"Views: {', '.join(summary['views'])}",
             "Parameters: " + "; ".join(f"{k} = {v}" for k, v in summary["parameters"].items()),
             "",
             f"Runs: {summary['runs']}  ok: {summary['ok']}  failed: {summary['failed']}",
             f"Computed: {summary['computed']}  cached: {summary['cached']}  "
             f"(cache hit rate {100 * summary['cache_hit_rate']:.0f} %)  retried: {summary['retried']}",
             f"Backend: {summary['backend']} ({summary['workers']} workers), "
             f"wall time {summary['seconds']:.1f} s", ""]
    fails = summary["failures"]
    lines.append(f"Failures ({len(fails)}):" if fails else "No failures.")
    for f in fails[:30]:
        lines += textwrap.wrap(f"- {f['case_id']} {f['params']}: {f['error_type']}: {f['error']}",
                               width=95, subsequent_indent="    ")
    if len(fails) > 30:
        lines.append(f"... and {len(fails) - 30} more (summary.json)")
    fig.text(0.06, 0.96, "\n".join(lines), va="top", family="monospace", fontsize=7.5)
    return fig


def write_study_figures(result, summary: dict) -> list[Path]:
    """PNG figures and ``study.pdf`` for a :class:`regtrack.study.run.StudyResult`;
    ``summary`` (:func:`regtrack.study.run.summary`) is the PDF's first page."""
    from matplotlib.backends.backend_pdf import PdfPages

    st = result.study
    names = list(st.parameters)
    figures: list[tuple[str, Figure]] = []
    if "c1" in names:
        for (case_id, view, others), rows in fig8_groups(result.rows, names).items():
            extra = " ".join(f"{k}={v}" for k, v in others)
            title = f"{st.name}: {case_id} {view}" + (f" ({extra})" if extra else "")
            figures.append((_slug(f"figure8_{case_id}_{view}" + (f"_{extra}" if extra else "")),
                            figure8(rows, title=title)))
    else:
        log.info("figure8 skipped: c1 is not a varied parameter of study %s", st.name)
    if any(r.get("d_T") is not None for r in result.rows):
        figures.append(("d_T", dt_figure(result.rows, names, title=f"{st.name}: d_T")))
    written = []
    for name, fig in figures:
        if (name == "d_T" and "d_T" in st.outputs) or (name != "d_T" and "figure8" in st.outputs):
            written.append(_io.save_figure(fig, st.out_dir / f"{name}.png"))
    if "pdf" in st.outputs:
        with _io.atomic_path(st.out_dir / "study.pdf") as tmp:
            with PdfPages(tmp) as pdf:
                pdf.savefig(summary_page(summary))
                for _, fig in figures:
                    pdf.savefig(fig)
        written.append(st.out_dir / "study.pdf")
    return written


def _validation(su: dict) -> str:
    """``"\nsurrogate's held-out nodal error, median: CC 0.26 mm"``: each view's validation."""
    parts = [f"{v} {d['median_mm']:.2g} mm" for v, d in (su.get("views") or {}).items()
             if d and d.get("median_mm") is not None]
    return f"\nsurrogate's held-out nodal error, median: {', '.join(parts)}" if parts else ""


def calibration_figure(result) -> Figure:
    """Score S (%) on the calibration grid, D-infeasible points crossed, optimum starred.

    Two calibrated parameters: a scatter map over (first, second); one: S against it.
    """
    names = list(result.bounds)
    fig = Figure(figsize=(6.4, 4.8), layout="constrained")
    ax = fig.subplots()
    ok = [e for e in result.grid if math.isfinite(e.score)]
    feas = [e for e in ok if e.violation == 0]
    infeas = [e for e in ok if e.violation > 0]
    opt = result.optimum
    su = getattr(result, "surrogate", None)
    path_label = "full runs at the surrogate's optima" if su else "optimiser"
    if len(names) == 1:
        n = names[0]
        pts = sorted(ok, key=lambda e: e.params[n])
        ax.plot([e.params[n] for e in pts], [e.score for e in pts], "o-", label="grid")
        ax.plot([e.params[n] for e in infeas], [e.score for e in infeas], "rx", ms=10,
                label="D outside range")
        ax.plot([e.params[n] for e in result.path], [e.score for e in result.path], ".",
                color="0.5", label=path_label)
        ax.plot([opt.params[n]], [opt.score], "*", ms=16, color="gold", mec="k", label="optimum")
        ax.set_xlabel(n)
        ax.set_ylabel(f"S = {result.objective} (%)")
    else:
        a, b = names[:2]
        sc = ax.scatter([e.params[a] for e in ok], [e.params[b] for e in ok],
                        c=[e.score for e in ok], s=160, cmap="viridis")
        fig.colorbar(sc, ax=ax, label=f"S = {result.objective} (%)")
        ax.plot([e.params[a] for e in infeas], [e.params[b] for e in infeas], "rx", ms=12,
                label="D outside range")
        ax.plot([e.params[a] for e in result.path], [e.params[b] for e in result.path], ".-",
                color="0.5", lw=0.6, label=path_label)
        ax.plot([opt.params[a]], [opt.params[b]], "*", ms=18, color="gold", mec="k",
                label="optimum")
        ax.set_xlabel(a)
        ax.set_ylabel(b)
        (a0, a1), (b0, b1) = result.bounds[a], result.bounds[b]
        ax.set_ylim(b0 - 0.03 * (b1 - b0), b1 + 0.03 * (b1 - b0))  # the whole calibrated box
        if a == "c1":
            from matplotlib.ticker import FormatStrFormatter, NullFormatter

            ax.set_xscale("log")
            ax.set_xlim(a0 / (a1 / a0) ** 0.03, a1 * (a1 / a0) ** 0.03)
            ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
            # under a decade the major ticks are too few: label the minor ones too
            ax.xaxis.set_minor_formatter(FormatStrFormatter("%g") if a1 / a0 < 10
                                         else NullFormatter())
        else:
            ax.set_xlim(a0 - 0.03 * (a1 - a0), a1 + 0.03 * (a1 - a0))
    del feas
    if su:  # where the surrogate's search cannot tell the scores apart
        iv = su["interval"]
        if len(names) == 1:
            ax.axvspan(*iv[names[0]], color="C1", alpha=0.15,
                       label=f"surrogate uncertainty (S within {su['tolerance']:.2g} %)")
        else:
            from matplotlib.patches import Rectangle

            (a0, a1), (b0, b1) = iv[names[0]], iv[names[1]]
            ax.add_patch(Rectangle((a0, b0), a1 - a0, b1 - b0, fill=False, ec="C1", lw=1.5,
                                   label=f"surrogate uncertainty (S within {su['tolerance']:.2g} %)"))
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    lo, hi = result.d_range
    ax.set_title(f"calibration of {result.case_id}: " + ", ".join(
        f"{k} = {v:g}" for k, v in opt.params.items()) + f"  (D in [{lo:g}, {hi:g}])"
        + (f"\nglobal search on the surrogate, every S from a full simulation{_validation(su)}"
           if su else ""), fontsize=9)
    return fig


