"""Tracking overlays on the real mammograms, outputs, and the case-report section.

Axes are in mm of the real canonical frame (chest wall on the left, as the other report
figures); the DICOM pixel positions are in the JSON.  Drawn per view:

* the real image, breast contour (blue) and annotated tumour (blue, dashed);
* the MRI prediction: a red ``+`` with circles of 1 and 2 sigma, and the projected
  outline of a tracked region (red, dashed);
* a curve predicted from the other view: orange, inside its 1-sigma band, with the most
  likely point (star); the marked point itself (green ``x``) in its own view;
* the truth, when known (black ``x``).

Hook into the case PDF (``regtrack.report.pdf``): ``fig = plt.figure(figsize=(8.27,
11.69)); draw_tracking_page(fig, result, reals); pdf.savefig(fig)`` with ``reals`` the
real :class:`~regtrack.views.MammogramView` per view (``ViewOutcome.real``).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.tracking.track import TrackResult

MRI = "tab:red"
CURVE = "tab:orange"
REAL = "tab:blue"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _band(seg, every: int = 4):
    """Polygon(s) of the curve's 1-sigma band (union of discs along it)."""
    import shapely
    from shapely.geometry import Point

    sigma = np.nan_to_num(seg.sigma_mm, nan=0.0)  # NaN: no uncertainty model, the curve only
    discs = [Point(*p).buffer(max(s, 1e-3), quad_segs=8)
             for p, s in zip(seg.polyline_mm[::every], sigma[::every])]
    u = shapely.union_all(discs)
    return list(getattr(u, "geoms", [u]))


def draw_view(ax, view: str, result: TrackResult, real=None, *, truth=None) -> None:
    """Draw the tracking results of ``view`` on ``ax`` (mm, real canonical frame)."""
    from matplotlib.patches import Circle

    from regtrack.report.figures import image_extent

    if real is not None:
        if real.image is not None:
            ax.imshow(real.image, cmap="gray", extent=image_extent(real), vmin=0, vmax=1)
        ax.plot(*np.asarray(real.breast_contour).T, color=REAL, lw=1.0, label="real breast")
        for k, t in enumerate(real.tumour_contours):
            t = np.vstack([t, t[:1]])
            ax.plot(*t.T, color=REAL, lw=1.0, ls="--", label="annotated tumour" if k == 0 else None)
    title = [f"{view}"]
    pts = []
    if result.mri is not None and view in result.mri.views:
        p = result.mri.views[view]
        if p.outline_mm is not None:
            o = np.vstack([p.outline_mm, p.outline_mm[:1]])
            ax.plot(*o.T, color=MRI, lw=1.0, ls="--", label="predicted outline")
        for k in (1, 2) if p.sigma_mm is not None else ():
            ax.add_patch(Circle(tuple(p.xy_mm), k * p.sigma_mm, fill=False, color=MRI,
                                lw=1.0, ls="-" if k == 1 else ":"))
        ax.plot(*p.xy_mm, "+", color=MRI, ms=12, mew=2, label=f"MRI {result.mri.kind} (±1σ, 2σ)")
        pts.append(p.xy_mm)
        where = "" if p.px is None else f" → px ({p.px[0]:.0f}, {p.px[1]:.0f})"
        title.append(f"{result.mri.kind}{where}"
                     + ("" if p.sigma_mm is None else f" ± {p.sigma_mm:.1f} mm"))
    for seg in result.segments:
        if seg.target_view == view:
            for g in _band(seg):
                ax.fill(*np.asarray(g.exterior.coords).T, color=CURVE, alpha=0.25, lw=0)
            for k, (a, b) in enumerate(seg.parts):
                lab = f"from {seg.source_view} ({seg.length_mm:.0f} mm)" if k == 0 else None
                ax.plot(*seg.polyline_mm[a:b].T, color=CURVE, lw=2.0, label=lab)
            pts.append(seg.polyline_mm)
            if seg.most_likely is not None:
                ax.plot(*seg.most_likely["xy_mm"], "*", color=CURVE, mec="k", ms=12,
                        label="most likely")
            title.append(f"curve {seg.length_mm:.0f} mm")
        if seg.source_view == view:
            ax.plot(*seg.source_mm, "x", color="tab:green", ms=10, mew=2, label="marked point")
            pts.append(seg.source_mm)
    for src_view, cp in result.contours.items():
        if src_view != view and len(cp.region_mm) > 2:
            r = np.vstack([cp.region_mm, cp.region_mm[:1]])
            ax.fill(*r.T, color=CURVE, alpha=0.2, lw=0)
            ax.plot(*r.T, color=CURVE, lw=1.2, ls="--", label=f"region from {src_view} contour")
            title.append("contour region")
        elif src_view == view:
            pts_src = np.array([s.source_mm for s in cp.segments])
            ax.plot(*np.vstack([pts_src, pts_src[:1]]).T, color="tab:green", lw=1.2,
                    label="marked contour")
    if truth is not None and view in truth:
        ax.plot(*np.asarray(truth[view], float), "x", color="k", ms=9, mew=2, label="truth")
    ax.set_title(": ".join([title[0], ", ".join(title[1:])]) if len(title) > 1 else title[0],
                 fontsize=9)
    ax.set_aspect("equal")
    if real is None or real.image is None:
        ax.invert_yaxis()
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=6, loc="lower left")


def view_figure(view: str, result: TrackResult, real=None, *, truth=None):
    """One view's overlay as a figure."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 6.5))
    draw_view(ax, view, result, real, truth=truth)
    fig.tight_layout()
    return fig


def sigma_text(sigma_mm: float | None, terms: dict) -> str:
    """`` ± s mm (residual a, rotation b, model c, nipple d)``: a 1-sigma radius and its
    terms (:mod:`regtrack.tracking.uncertainty`); empty without one."""
    if sigma_mm is None:
        return ""
    names = {"registration_residual": "residual", "rotation": "rotation", "model": "model",
             "nipple": "nipple"}
    parts = ", ".join(f"{names[k]} {v:.1f}" for k, v in terms.items() if k in names)
    return f" ± {sigma_mm:.1f} mm ({parts})"


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def summary_lines(result: TrackResult) -> list[str]:
    """Plain-text summary (report section body)."""
    lines = []
    if result.mri is not None:
        lps = ", ".join(f"{v:.1f}" for v in result.mri.lps_mm)
        lines.append(f"{result.mri.description}: LPS ({lps}) mm")
        for v, p in result.mri.views.items():
            px = "" if p.px is None else f", px (row {p.px[0]:.1f}, col {p.px[1]:.1f})"
            t = ("" if p.truth_distance_mm is None
                 else f"; {p.truth_distance_mm:.2f} mm from the truth")
            lines.append(f"  {v}: ({p.xy_mm[0]:.1f}, {p.xy_mm[1]:.1f}) mm{px}"
                         f"{sigma_text(p.sigma_mm, p.terms_mm)}{t}")
        lines += [f"  note: {n}" for n in result.mri.notes]
    for s in result.segments:
        src = ("" if s.source_px is None
               else f" px (row {s.source_px[0]:.0f}, col {s.source_px[1]:.0f})")
        lines.append(f"{s.source_view}{src} -> {s.target_view}: curve of {s.length_mm:.1f} mm "
                     f"(ray {s.thickness_mm:.1f} mm through the compressed breast)")
        if s.most_likely is not None:
            m = s.most_likely
            t = ("" if m.get("truth_distance_mm") is None
                 else f"; {m['truth_distance_mm']:.2f} mm from the truth")
            lines.append(f"  most likely ({m.get('lesion')}): "
                         f"({m['xy_mm'][0]:.1f}, {m['xy_mm'][1]:.1f}) mm,"
                         f" ray passes {m['reference_distance_mm']:.1f} mm from it in the MRI{t}")
        if s.truth_distance_mm is not None:
            lines.append(f"  the curve passes {s.truth_distance_mm:.2f} mm from the true lesion")
        lines += [f"  note: {n}" for n in s.notes]
    return lines


def report_section(result: TrackResult) -> dict:
    """The case-report section: ``{"title", "lines", "results"}`` (JSON-ready)."""
    return {"title": f"Lesion tracking: case {result.case_id}", "lines": summary_lines(result),
            "results": result.to_dict()}


def draw_tracking_page(fig, result: TrackResult, reals: dict | None = None, *, truth=None) -> None:
    """Draw the tracking section (text and one panel per view) on an A4 ``fig``."""
    reals = reals or {}
    views = list(result.views) or sorted(set(reals))
    fig.text(0.06, 0.95, f"Lesion tracking: case {result.case_id}", fontsize=14, weight="bold")
    body = [w for ln in summary_lines(result)
            for w in (textwrap.wrap(ln, 115, subsequent_indent=" " * (_indent(ln) + 4)) or [""])]
    fig.text(0.06, 0.92, "\n".join(body[:22]), fontsize=7, va="top", family="monospace")
    n = max(len(views), 1)
    for k, v in enumerate(views):
        ax = fig.add_axes([0.07 + k * 0.92 / n, 0.06, 0.92 / n - 0.08, 0.5])
        draw_view(ax, v, result, reals.get(v), truth=truth)


def write_outputs(result: TrackResult, out_dir: str | Path, *, reals: dict | None = None,
                  truth=None, pdf: bool = True) -> list[Path]:
    """``tracking.json``, ``track_<view>.png`` overlays and ``tracking.pdf`` (one page)."""
    out = Path(out_dir)
    reals = reals or {}
    paths = [_io.write_json(out / "tracking.json", {**result.to_dict(),
                                                    "summary": summary_lines(result)})]

    for v in result.views:
        paths.append(_io.save_figure(view_figure(v, result, reals.get(v), truth=truth),
                                 out / f"track_{v.lower()}.png"))
    if pdf:
        plt = _plt()
        from matplotlib.backends.backend_pdf import PdfPages

        fig = plt.figure(figsize=(8.27, 11.69))
        try:
            draw_tracking_page(fig, result, reals, truth=truth)
            with _io.atomic_path(out / "tracking.pdf") as tmp, PdfPages(tmp) as doc:
                doc.savefig(fig)
        finally:
            plt.close(fig)
        paths.append(out / "tracking.pdf")
    return paths
