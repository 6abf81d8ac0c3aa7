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
                 theta_deg: float, title: str) -> None:
    """Real (blue) and virtual (red) contours, centroids (+) and nipple (o) on ``ax``."""
    vb = alignment.transform(virtual.breast_contour, theta_deg)
    ax.plot(*real.breast_contour.T, color=REAL, lw=1.6, label="real breast")
    ax.plot(*vb.T, color=VIRTUAL, lw=1.6, label="virtual breast")
    ax.plot(*centroid(real.breast_contour), "+", color=REAL, ms=11, mew=2)
    ax.plot(*centroid(vb), "+", color=VIRTUAL, ms=11, mew=2)
    for k, t in enumerate(real.tumour_contours):
        ax.plot(*_closed(t).T, color=REAL, lw=1.2, ls="--", label="real tumour" if k == 0 else None)
        ax.plot(*centroid(t), "x", color=REAL, ms=7, mew=1.5)
    for k, t in enumerate(virtual.tumour_contours):
        vt = alignment.transform(t, theta_deg)
        ax.plot(*_closed(vt).T, color=VIRTUAL, lw=1.2, ls="--", label="virtual tumour" if k == 0 else None)
        ax.plot(*centroid(vt), "x", color=VIRTUAL, ms=7, mew=1.5)
    ax.plot(*alignment.nipple, "o", color="k", ms=5, label="nipple")
    ax.set_title(title, fontsize=10)
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=6, loc="best")


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


def images_figure(real: MammogramView, virtual: MammogramView, alignment: Alignment | None = None):
    """Real mammogram beside the X-ray-like virtual image, with their contours."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    for ax, v, name, col in ((axes[0], real, "real", REAL), (axes[1], virtual, "virtual", VIRTUAL)):
        if v.image is not None:
            ax.imshow(v.image, cmap="gray", extent=image_extent(v), vmin=0, vmax=1)
        ax.plot(*v.breast_contour.T, color=col, lw=1.2)
        for t in v.tumour_contours:
            ax.plot(*_closed(t).T, color="tab:orange", lw=1.0)
        ax.plot(*v.nipple, "o", color="tab:orange", ms=4)
        ax.set_title(f"{name} {v.view} ({v.laterality})", fontsize=10)
        ax.set_aspect("equal")
        if v.image is None:
            ax.invert_yaxis()
        ax.set_xlabel("x (mm)")
    fig.tight_layout()
    return fig


def virtual_figure(virtual: MammogramView):
    """The X-ray-like virtual mammogram with its contours (no real mammogram to compare)."""
    plt = _plt()
    fig, ax = plt.subplots(1, 1, figsize=(6, 5))
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
    fig.tight_layout()
    return fig


