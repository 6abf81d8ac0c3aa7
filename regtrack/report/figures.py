"""Figures of one view: contour overlays before/after the rotation and the two images.

All axes are in mm in the canonical 2-D frame of :mod:`regtrack.views` (x from the chest
wall to the nipple, y down).  The virtual contours are mapped into the real frame by the
alignment: ``n_p + R(theta) (v - n_v)``, with ``theta = 0`` ("before": superimposed at
the nipple only) and ``theta = theta_p`` ("after"), as in Figure 9 of Lapuebla-Ferri et al.
"""

from __future__ import annotations

import numpy as np

from regtrack.registration.align import Alignment
from regtrack.registration.geometry import polygon
from regtrack.views import MammogramView

REAL = "tab:blue"
VIRTUAL = "tab:red"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def image_extent(v: MammogramView) -> tuple[float, float, float, float]:
    """imshow extent (left, right, bottom, top) in mm for ``v.image``."""
    h, w = v.image.shape[:2]
    sy, sx = v.pixel_spacing
    x0, y0 = v.origin
    return (x0 - sx / 2, x0 + (w - 0.5) * sx, y0 + (h - 0.5) * sy, y0 - sy / 2)


def centroid(contour: np.ndarray) -> np.ndarray:
    """Area centroid (mm) of a contour closed by its chord (the metrics' convention)."""
    c = polygon(np.asarray(contour, float)).centroid
    return np.array([c.x, c.y])


def _closed(c: np.ndarray) -> np.ndarray:
    return np.vstack([c, c[:1]])


def draw_overlay(ax, real: MammogramView, virtual: MammogramView, alignment: Alignment, *,
                 theta_deg: float, title: str, legend: bool = True) -> None:
    """Real (blue) and virtual (red) contours on ``ax``: breast (solid) with its area
    centroid (+), tumour (dashed) with its centroid (x), and the nipple (black dot)."""
    vb = alignment.transform(virtual.breast_contour, theta_deg)
    ax.plot(*real.breast_contour.T, color=REAL, lw=1.6, label="real breast")
    ax.plot(*vb.T, color=VIRTUAL, lw=1.6, label="virtual breast")
    ax.plot(*centroid(real.breast_contour), "+", color=REAL, ms=11, mew=2,
            label="real breast centroid")
    ax.plot(*centroid(vb), "+", color=VIRTUAL, ms=11, mew=2, label="virtual breast centroid")
    for k, t in enumerate(real.tumour_contours):
        ax.plot(*_closed(t).T, color=REAL, lw=1.2, ls="--", label="real tumour" if k == 0 else None)
        ax.plot(*centroid(t), "x", color=REAL, ms=7, mew=1.5,
                label="real tumour centroid" if k == 0 else None)
    for k, t in enumerate(virtual.tumour_contours):
        vt = alignment.transform(t, theta_deg)
        ax.plot(*_closed(vt).T, color=VIRTUAL, lw=1.2, ls="--", label="virtual tumour" if k == 0 else None)
        ax.plot(*centroid(vt), "x", color=VIRTUAL, ms=7, mew=1.5,
                label="virtual tumour centroid" if k == 0 else None)
    ax.plot(*alignment.nipple, "o", color="k", ms=5, label="nipple (superposed)")
    ax.set_title(title, fontsize=10)
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    if legend:
        ax.legend(fontsize=6.5, loc="best")


#: legend order of :func:`draw_overlay`'s artists: real, then virtual, then the nipple
LEGEND_ORDER = ("real breast", "real breast centroid", "real tumour", "real tumour centroid",
                "virtual breast", "virtual breast centroid", "virtual tumour",
                "virtual tumour centroid", "nipple (superposed)")


def overlay_legend(fig, ax, *, y: float = 0.0, fontsize: float = 7.5) -> None:
    """One legend for a row of :func:`draw_overlay` panels, from ``ax``'s artists, in two
    rows (real above virtual; matplotlib fills legend columns top to bottom)."""
    by_label = dict(zip(*reversed(ax.get_legend_handles_labels())))
    labels = [lab for lab in LEGEND_ORDER if lab in by_label]
    labels += [lab for lab in by_label if lab not in labels]
    real = [lab for lab in labels if lab.startswith("real")]
    virt = [lab for lab in labels if lab.startswith("virtual")]
    other = [lab for lab in labels if lab not in real and lab not in virt]
    ncol = max(len(real), len(virt)) + (1 if other else 0)
    rows = [real + [""] * (ncol - len(real)), virt + other + [""] * (ncol - len(virt) - len(other))]
    order = [rows[r][c] for c in range(ncol) for r in range(2)]
    from matplotlib.lines import Line2D

    blank = Line2D([], [], lw=0)
    fig.legend([by_label.get(lab, blank) for lab in order], order, loc="lower center",
               ncol=ncol, fontsize=fontsize, frameon=False, bbox_to_anchor=(0.5, y))


def draw_images(ax_real, ax_virtual, real: MammogramView, virtual: MammogramView,
                alignment: Alignment) -> None:
    """The real mammogram and the virtual one side by side on the same axes (mm of the
    real image's frame): the virtual image is shifted so that its nipple lies on the real
    nipple (``theta = 0``; where the registration searched the detected nipple along the
    skin line, the point it chose, and the detected one as a cross), and both axes get the
    union of the two images' extents."""
    shift = np.asarray(alignment.translation, float)
    boxes = []
    for ax, v, name, col, d in ((ax_real, real, "real", REAL, np.zeros(2)),
                                (ax_virtual, virtual, "virtual", VIRTUAL, shift)):
        if v.image is not None:
            left, right, bottom, top = image_extent(v)
            ext = (left + d[0], right + d[0], bottom + d[1], top + d[1])
            ax.imshow(v.image, cmap="gray", extent=ext, vmin=0, vmax=1)
            boxes.append(ext)
        ax.plot(*(v.breast_contour + d).T, color=col, lw=1.2, label=f"{name} breast")
        for k, t in enumerate(v.tumour_contours):
            ax.plot(*(_closed(t) + d).T, color="tab:orange", lw=1.0,
                    label=f"{name} tumour" if k == 0 else None)
        nip = alignment.nipple if name == "real" else np.asarray(v.nipple) + d
        ax.plot(*nip, "o", color="tab:orange", ms=4, label="nipple")
        det = alignment.detected_nipple
        if name == "real" and det is not None and np.linalg.norm(det - nip) > 0.5:
            ax.plot(*det, "x", color="tab:orange", ms=5, label="nipple detected")
        ax.set_title(f"{name} {v.view}" + (" (shifted to the real nipple)" if name == "virtual"
                                            else ""), fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.legend(fontsize=6.5, loc="lower left")
    ax_real.set_ylabel("y (mm)")
    pts = [real.breast_contour, virtual.breast_contour + shift]
    xs = [b[0] for b in boxes] + [b[1] for b in boxes] + [float(p[:, 0].min()) for p in pts] \
        + [float(p[:, 0].max()) for p in pts]
    ys = [b[2] for b in boxes] + [b[3] for b in boxes] + [float(p[:, 1].min()) for p in pts] \
        + [float(p[:, 1].max()) for p in pts]
    for ax in (ax_real, ax_virtual):
        ax.set_xlim(min(xs), max(xs))
        ax.set_ylim(max(ys), min(ys))  # y down


def overlay_figure(real: MammogramView, virtual: MammogramView, alignment: Alignment):
    """Two panels: superimposed at the nipple (theta = 0) and after rotation by theta_p."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    draw_overlay(axes[0], real, virtual, alignment, theta_deg=0.0,
                 title=f"{real.view}: superimposed at the nipple (θ = 0°)")
    draw_overlay(axes[1], real, virtual, alignment, theta_deg=alignment.theta_p,
                 title=f"{real.view}: rotated by θp = {alignment.theta_p:.2f}°")
    fig.tight_layout()
    return fig


def images_figure(real: MammogramView, virtual: MammogramView, alignment: Alignment):
    """Real mammogram beside the X-ray-like virtual image on the same axes
    (:func:`draw_images`)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    draw_images(axes[0], axes[1], real, virtual, alignment)
    fig.tight_layout()
    return fig


def draw_virtual(ax, virtual: MammogramView) -> None:
    """The X-ray-like virtual mammogram with its contours on ``ax``."""
    if virtual.image is not None:
        ax.imshow(virtual.image, cmap="gray", extent=image_extent(virtual), vmin=0, vmax=1)
    else:
        ax.invert_yaxis()
    ax.plot(*virtual.breast_contour.T, color=VIRTUAL, lw=1.2, label="breast contour")
    for k, t in enumerate(virtual.tumour_contours):
        ax.plot(*_closed(t).T, color="tab:orange", lw=1.0, label="tumour" if k == 0 else None)
    ax.plot(*virtual.nipple, "o", color="tab:orange", ms=4, label="nipple")
    ax.set_title(f"virtual {virtual.view} ({virtual.laterality})", fontsize=10)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=7, loc="lower left")


def virtual_figure(virtual: MammogramView):
    """The X-ray-like virtual mammogram with its contours (no real mammogram to compare)."""
    plt = _plt()
    fig, ax = plt.subplots(1, 1, figsize=(6, 5))
    draw_virtual(ax, virtual)
    fig.tight_layout()
    return fig


