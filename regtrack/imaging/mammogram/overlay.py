"""Overlay figure of an extracted view: image, breast mask outline, skin contour,
chest-wall line, nipple and tumour contours, all drawn in mm of the canonical frame."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from regtrack._io import save_figure
from regtrack.views import MammogramView


def write_overlay(view: MammogramView, path: str | os.PathLike, *, title: str | None = None,
                  dpi: int = 110) -> Path:
    """Write a PNG overlay of ``view`` (matplotlib, Agg backend) atomically to ``path``."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    img = view.image if view.image is not None else np.zeros((2, 2))
    h, w = img.shape
    sy, sx = view.pixel_spacing
    x0, y0 = view.origin
    extent = (x0 - sx / 2, x0 + (w - 0.5) * sx, y0 + (h - 0.5) * sy, y0 - sy / 2)
    aspect = (extent[2] - extent[3]) / (extent[1] - extent[0])
    fig = Figure(figsize=(6.0, 6.0 * aspect + 0.6))
    ax = fig.add_subplot(111)
    ax.imshow(img, cmap="gray", extent=extent, vmin=0, vmax=max(float(img.max()), 1e-6))
    if view.breast_mask is not None:
        ax.contour(np.linspace(extent[0], extent[1], w), np.linspace(extent[3], extent[2], h),
                   view.breast_mask.astype(float), levels=[0.5], colors="yellow",
                   linewidths=0.5, linestyles="dotted")
    c = np.asarray(view.breast_contour)
    ax.plot(c[:, 0], c[:, 1], "-", color="lime", lw=1.2, label="skin contour")
    ax.plot(c[[0, -1], 0], c[[0, -1], 1], "o", color="lime", ms=4)
    pect = (view.meta.get("pectoral") or {}).get("line_mm")
    if pect:
        p = np.asarray(pect)
        ax.plot(p[:, 0], p[:, 1], "--", color="orange", lw=1.2, label="pectoral line")
    for k, t in enumerate(view.tumour_contours):
        t = np.vstack([t, t[:1]])
        ax.plot(t[:, 0], t[:, 1], "-", color="red", lw=1.2, label="tumour" if k == 0 else None)
    ax.plot(*view.nipple, "+", color="cyan", ms=14, mew=2, label="nipple")
    conf = (view.meta.get("nipple") or {}).get("confidence")
    ttl = title or f"{view.laterality}{view.view}  {Path(view.source).name}"
    if conf is not None:
        ttl += f"  (nipple conf. {conf:.2f})"
    ax.set_title(ttl, fontsize=9)
    ax.set_xlabel("x (mm): chest wall -> nipple")
    ax.set_ylabel("y (mm): " + ("medial" if view.view == "CC" else "infero-medial") + " down")
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=dpi)
