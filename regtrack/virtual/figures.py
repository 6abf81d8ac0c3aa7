"""PNG figures of a virtual mammogram: the X-ray-like image and a contour overlay (mm axes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.virtual.project import VirtualMammogram


def _extent(vm: VirtualMammogram) -> tuple[float, float, float, float]:
    """imshow extent (left, right, bottom, top) in mm, pixel centres on the grid."""
    h, w = vm.grid.shape
    s = vm.grid.spacing
    x0, y0 = vm.grid.origin
    return (x0 - s / 2, x0 + (w - 0.5) * s, y0 + (h - 0.5) * s, y0 - s / 2)


def save_xray_png(vm: VirtualMammogram, path: str | Path) -> Path:
    """Write the X-ray-like image (8-bit grey, canonical orientation, one pixel per grid pixel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = vm.view.image if vm.view.image is not None else vm.view.breast_mask.astype(float)
    with _io.atomic_path(path) as tmp:
        plt.imsave(tmp, np.asarray(img, float), cmap="gray", vmin=0.0, vmax=1.0, format="png")
    return Path(path)


def save_overlay_png(vm: VirtualMammogram, path: str | Path, *, title: str = "",
                     dpi: int = 120) -> Path:
    """Write the image with the open breast contour, the chest-wall side, the tumour
    contour(s) and the nipple drawn on it (axes in mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = vm.view
    img = v.image if v.image is not None else v.breast_mask.astype(float)
    fig, ax = plt.subplots(figsize=(6, 6 * img.shape[0] / max(img.shape[1], 1) + 0.6))
    try:
        ax.imshow(img, cmap="gray", extent=_extent(vm), vmin=0, vmax=1)
        c = vm.closed_contour
        ax.plot(*np.vstack([c, c[:1]]).T, color="0.6", lw=0.8, ls="--", label="outline")
        ax.plot(*v.breast_contour.T, color="tab:cyan", lw=1.5, label="breast contour")
        for k, t in enumerate(v.tumour_contours):
            ax.plot(*np.vstack([t, t[:1]]).T, color="tab:red", lw=1.2,
                    label="tumour" if k == 0 else None)
        ax.plot(*v.nipple, "o", color="tab:orange", ms=5, label="nipple")
        ax.set_xlabel("x (mm): posterior -> anterior")
        ax.set_ylabel("y (mm): " + ("medial" if v.view == "CC" else "infero-medial"))
        ax.set_title(title or f"virtual {v.view} ({v.laterality})")
        ax.legend(loc="lower left", fontsize=7)
        ax.set_aspect("equal")
        fig.tight_layout()
    except BaseException:
        plt.close(fig)
        raise
    return _io.save_figure(fig, path, dpi=dpi)
