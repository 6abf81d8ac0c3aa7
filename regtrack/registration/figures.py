"""Overlay PNG of a registration: real contours, aligned virtual contours, nipple (mm axes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.registration.align import Alignment
from regtrack.views import MammogramView


def save_registration_png(real: MammogramView, alignment: Alignment, path: str | Path, *,
                          title: str = "", dpi: int = 120) -> Path:
    """Draw the real image (if any), the real contours (solid) and the virtual contours
    after nipple superposition and rotation by theta_p (dashed), in the real frame (mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 7))
    try:
        if real.image is not None:
            h, w = real.image.shape
            sy, sx = real.pixel_spacing
            x0, y0 = real.origin
            ax.imshow(real.image, cmap="gray", vmin=0, vmax=1,
                      extent=(x0 - sx / 2, x0 + (w - 0.5) * sx, y0 + (h - 0.5) * sy, y0 - sy / 2))
        else:
            ax.invert_yaxis()
        ax.plot(*np.asarray(real.breast_contour).T, color="tab:cyan", lw=1.5, label="real breast")
        ax.plot(*alignment.breast_contour.T, color="tab:orange", lw=1.2, ls="--",
                label="virtual breast")
        for k, t in enumerate(real.tumour_contours):
            ax.plot(*np.vstack([t, t[:1]]).T, color="tab:red", lw=1.2,
                    label="real tumour" if k == 0 else None)
        for k, t in enumerate(alignment.tumour_contours):
            ax.plot(*np.vstack([t, t[:1]]).T, color="tab:pink", lw=1.2, ls="--",
                    label="virtual tumour" if k == 0 else None)
        ax.plot(*alignment.nipple, "o", color="yellow", mec="k", ms=6, label="nipple")
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title or f"{alignment.view}: theta_p = {alignment.theta_p:.2f} deg")
        ax.legend(loc="lower left", fontsize=7)
        fig.tight_layout()
    except BaseException:
        plt.close(fig)
        raise
    return _io.save_figure(fig, path, dpi=dpi)
