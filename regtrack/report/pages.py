"""The pages of the case report, each drawn on an A4 matplotlib figure.

Coordinates are figure fractions (0 bottom, 1 top).  Every number goes through
:mod:`regtrack.report.fmt`; every table drops its empty columns.
"""

from __future__ import annotations

import textwrap

from regtrack.mechanics.pictures import draw_sequence
from regtrack.report import figures as F
from regtrack.report.fmt import drop_empty_columns, num

A4 = (8.27, 11.69)
OK_COLOUR, FLAG_COLOUR, NA_COLOUR, HEAD_COLOUR = "#d8f0d8", "#ffd2a6", "#eeeeee", "#dde3ee"


def title(fig, text: str, *, y: float = 0.962, size: float = 14) -> None:
    fig.text(0.05, y, text, fontsize=size, weight="bold")


def table(ax, head: list[str], rows: list[list[str]], *, fontsize: float = 8,
          colours: list[list[str]] | None = None, col_widths: list[float] | None = None) -> None:
    """A table filling ``ax`` (header shaded, optional per-cell colours)."""
    ax.axis("off")
    if not rows:
        ax.text(0.0, 0.5, "none", fontsize=fontsize, va="center")
        return
    t = ax.table(cellText=rows, colLabels=head, cellColours=colours, colWidths=col_widths,
                 cellLoc="center", bbox=[0, 0, 1, 1])
    t.auto_set_font_size(False)
    t.set_fontsize(fontsize)
    for (r, _c), cell in t.get_celld().items():
        cell.set_edgecolor("#b0b0b0")
        cell.set_linewidth(0.5)
        if r == 0:
            cell.set_facecolor(HEAD_COLOUR)
            cell.get_text().set_weight("bold")


def flow_table(fig, y: float, heading: str, head: list[str], rows: list[list[str]], *,
               x: list[float], wrap: list[int], fontsize: float = 7.5, line: float = 0.0125
               ) -> float:
    """A table written row by row from ``y`` down (columns at ``x``, cells wrapped at
    ``wrap`` characters); returns the ``y`` below it."""
    fig.text(0.05, y, heading, fontsize=10, weight="bold", va="top")
    y -= 0.022
    if not rows:
        fig.text(x[0], y, "none", fontsize=fontsize, va="top", style="italic")
        return y - line - 0.012
    for k, row in enumerate([head, *rows]):
        cells = [textwrap.wrap(str(c), w) or [""] for c, w in zip(row, wrap)]
        for xc, lines in zip(x, cells):
            fig.text(xc, y, "\n".join(lines), fontsize=fontsize, va="top",
                     weight="bold" if k == 0 else "normal", linespacing=1.25)
        y -= line * max(len(c) for c in cells) + 0.004
        if k == 0:
            fig.add_artist(_rule(y + 0.002))
    return y - 0.014


def _rule(y: float):
    from matplotlib.lines import Line2D

    return Line2D([0.05, 0.95], [y, y], lw=0.5, color="0.6")


def same_limits(axes) -> None:
    """Give every axes the union of their data limits (keeping each axis' direction)."""
    xs = [a.get_xlim() for a in axes]
    ys = [a.get_ylim() for a in axes]
    x0, x1 = min(min(x) for x in xs), max(max(x) for x in xs)
    y0, y1 = min(min(y) for y in ys), max(max(y) for y in ys)
    for a, x, y in zip(axes, xs, ys):
        a.set_xlim((x0, x1) if x[0] <= x[1] else (x1, x0))
        a.set_ylim((y0, y1) if y[0] <= y[1] else (y1, y0))


def verdict_cells(checks, views: list[str]) -> tuple[list[str], list[list[str]], list[list[str]]]:
    """Rows "check, threshold, value per view" with the cell colours of the verdict."""
    names = list(dict.fromkeys(c.name for c in checks))
    head = ["Check", "Threshold", *views]
    rows, colours = [], []
    for name in names:
        by_view = {c.view: c for c in checks if c.name == name}
        first = next(iter(by_view.values()))
        row, col = [name, first.threshold], [HEAD_COLOUR, "white"]
        for v in views:
            c = by_view.get(v)
            if c is None or c.ok is None:
                row.append("–" if c is None else c.value)
                col.append(NA_COLOUR)
            else:
                row.append(c.value + ("  ✓" if c.ok else "  ✗"))
                col.append(OK_COLOUR if c.ok else FLAG_COLOUR)
        rows.append(row)
        colours.append(col)
    return head, rows, colours


def summary_page(fig, report, checks, verdict: str, metrics_head, metrics_rows, explanation: str,
                 header_lines: list[str]) -> None:
    """Page 1: case, mode, verdict, metrics and the overlays of every view at theta_p."""
    title(fig, f"regtrack report: case {report.case_id}", size=16)
    y = 0.94
    for line in [report.title, *header_lines]:
        if line:
            fig.text(0.05, y, line, fontsize=8.5, color="0.25", va="top")
            y -= 0.016
    flagged = any(c.ok is False for c in checks)
    colour = "0.2" if not checks else "#b35a00" if flagged else "#1d6b1d"
    y -= 0.008
    lines = textwrap.wrap("Verdict: " + verdict, 100)
    fig.text(0.05, y, "\n".join(lines), fontsize=10.5, weight="bold", va="top",
             color=colour)
    y -= 0.017 * (len(lines) - 1)
    views = [v.view for v in report.views]
    head, rows, colours = verdict_cells(checks, views)
    h = 0.022 * (len(rows) + 1)
    top = y - 0.03
    if rows:
        table(fig.add_axes([0.05, top - h, 0.9, h]), head, rows, colours=colours, fontsize=8,
              col_widths=[0.34, 0.18] + [0.48 / max(len(views), 1)] * len(views))
        fig.text(0.05, top - h - 0.006, "✓ within the threshold, ✗ flagged (see the "
                 "page of the view); thresholds: regtrack.report.verdict.", fontsize=6.5,
                 color="0.35", va="top")
        top -= h + 0.03
    fig.text(0.05, top, "Metrics", fontsize=10, weight="bold", va="top")
    mh, mr = drop_empty_columns(metrics_head, metrics_rows)
    h = 0.022 * (len(mr) + 1)
    table(fig.add_axes([0.05, top - 0.018 - h, 0.9, h]), mh, mr, fontsize=8)
    top -= 0.018 + h + 0.008
    expl = textwrap.wrap(explanation, 150)
    fig.text(0.05, top, "\n".join(expl), fontsize=6.5, va="top", color="0.2")
    top -= 0.0105 * len(expl) + 0.01  # the overlays start below the explanation
    aligned = [v for v in report.views if v.real is not None and v.alignment is not None]
    if aligned:
        n = len(aligned)
        w = 0.86 / n
        height = min(top - 0.09 - 0.03, 0.42)  # room for the axes' titles above them
        ax = None
        for k, v in enumerate(aligned):
            ax = fig.add_axes([0.08 + k * (w + 0.02), 0.09, w - 0.06, height])
            F.draw_overlay(ax, v.real, v.virtual, v.alignment, theta_deg=v.alignment.theta_p,
                           title=f"{v.view}: virtual rotated by θp = "
                                 f"{num(v.alignment.theta_p, 2, signed=True)}°", legend=False)
        F.overlay_legend(fig, ax, y=0.005)
    else:  # no registration: the virtual mammograms
        shown = [v for v in report.views if v.virtual is not None]
        w = 0.86 / max(len(shown), 1)
        for k, v in enumerate(shown):
            F.draw_virtual(fig.add_axes([0.08 + k * (w + 0.02), 0.06, w - 0.06, top - 0.12]),
                           v.virtual)


def steps_cells(steps: list[dict]) -> tuple[list[str], list[list[str]]]:
    """The simulation-steps table of a view, with units and without empty columns."""
    cols = (("step", "Step", lambda v: str(v).replace("-", " ")),
            ("D", "D (%)", lambda v: num(None if v is None else 100 * v, 1)),
            ("force_N", "Upper plate\nforce (N)", lambda v: num(v, 1)),
            ("max_penetration_mm", "Penetration\n(mm)", lambda v: num(v, 3)),
            ("behind_wall_mm", "Behind chest\nwall (mm)", lambda v: num(v, 2)),
            ("skin_overlap_mm", "Skin in\ntissue (mm)", lambda v: num(v, 1)),
            ("increments", "Load\nincrements", lambda v: num(v, 0)),
            ("iterations", "Newton\niterations", lambda v: num(v, 0)),
            ("seconds", "Time (s)", lambda v: num(v, 1)))
    head = [t for _, t, _ in cols]
    rows = [[f(s.get(k)) for k, _, f in cols] for s in steps]
    return drop_empty_columns(head, rows)


#: warnings printed on a view's page (the rest are counted; all are in the view's JSON)
MAX_WARNINGS = 4


def warning_lines(warnings: list[str], width: int = 165) -> list[str]:
    """The simulation's warnings as bulleted lines of at most ``width`` characters: the
    first ``MAX_WARNINGS`` in full, then how many more there are."""
    lines: list[str] = []
    for w in warnings[:MAX_WARNINGS]:
        lines += textwrap.wrap(f"• {w}", width, subsequent_indent="   ")
    if len(warnings) > MAX_WARNINGS:
        lines.append(f"   and {len(warnings) - MAX_WARNINGS} more in the view's simulation JSON")
    return lines


def view_page(fig, v) -> None:
    """One view: the compression sequence, its steps, the contours before and after the
    rotation, and the real beside the virtual image on the same axes."""
    title(fig, f"{v.view} view: compression, contours and images")
    seq = v.sequence
    if seq is not None:
        k = len(seq.steps)
        w = 0.9 / k
        axes = [fig.add_axes([0.07 + j * w, 0.745, w - 0.025, 0.18]) for j in range(k)]
        draw_sequence(axes, seq.points, seq.skin, seq.steps, seq.states, seq.plate_frame, seq.cut)
        same_limits(axes)
        for a in axes[1:]:  # same limits: the first panel's scale serves all
            a.set_ylabel("")
            a.tick_params(labelleft=False)
    elif v.pictures and v.pictures[0].is_file():
        import matplotlib.pyplot as plt

        ax = fig.add_axes([0.05, 0.745, 0.9, 0.18])
        ax.imshow(plt.imread(str(v.pictures[0])))
        ax.axis("off")
    head, rows = steps_cells(v.steps)
    top = 0.705
    if rows:
        fig.text(0.05, top, "Simulation steps", fontsize=9.5, weight="bold", va="top")
        h = 0.016 * (len(rows) + 2)
        table(fig.add_axes([0.05, top - 0.016 - h, 0.9, h]), head, rows, fontsize=7.5,
              col_widths=[0.22] + [0.78 / (len(head) - 1)] * (len(head) - 1))
        top -= 0.016 + h + 0.035
    lines = warning_lines(((v.simulation or {}).get("summary") or {}).get("warnings") or [])
    if lines:
        fig.text(0.05, top, "Simulation warnings", fontsize=9.5, weight="bold", va="top")
        fig.text(0.05, top - 0.018, "\n".join(lines), fontsize=6.5, va="top", color="#8a1c1c")
        top -= 0.018 + 0.0105 * len(lines) + 0.03
    if v.real is not None and v.alignment is not None:
        h = (top - 0.16) / 2
        a0 = fig.add_axes([0.08, top - h, 0.4, h])
        a1 = fig.add_axes([0.56, top - h, 0.4, h])
        F.draw_overlay(a0, v.real, v.virtual, v.alignment, theta_deg=0.0,
                       title=f"{v.view}: superposed at the nipple (θ = 0°)", legend=False)
        F.draw_overlay(a1, v.real, v.virtual, v.alignment, theta_deg=v.alignment.theta_p,
                       title=f"{v.view}: rotated by θp = {num(v.alignment.theta_p, 2, signed=True)}°",
                       legend=False)
        same_limits([a0, a1])
        F.overlay_legend(fig, a0, y=0.035 + h + 0.028, fontsize=7)
        b0 = fig.add_axes([0.08, 0.035, 0.4, h])
        b1 = fig.add_axes([0.56, 0.035, 0.4, h])
        F.draw_images(b0, b1, v.real, v.virtual, v.alignment)
    elif v.virtual is not None:
        F.draw_virtual(fig.add_axes([0.1, 0.05, 0.8, top - 0.1]), v.virtual)


def appendix_page(fig, sections: list[tuple[str, list[str], list[list[str]], list[float], list[int]]]
                  ) -> None:
    """The appendix: a title and each ``(heading, head, rows, x, wrap)`` table in turn."""
    names = ["ground truth" if h.startswith("Ground truth") else h.split(" (")[0].lower()
             for h, *_ in sections]
    names = ["model" if n == "patient model" else "settings" if n.startswith("settings") else n
             for n in names]
    title(fig, "Appendix: " + (", ".join(names[:-1]) + " and " + names[-1] if len(names) > 1
                               else names[0]), size=13)
    y = 0.935
    for heading, head, rows, x, wrap in sections:
        y = flow_table(fig, y, heading, head, rows, x=x, wrap=wrap)
