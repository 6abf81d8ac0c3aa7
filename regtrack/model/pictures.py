"""PNG pictures of a model: three orthogonal sections through the nipple and a 3-D view.

Sections are drawn in the model frame (mm): tissue tets cut by the plane in grey, tumour
tets in red, skin edges in green, fixed (chest-wall) nodes near the plane in blue, the
nipple as a black cross.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regtrack import _io
from regtrack.model.types import BreastModel

SECTIONS = (("sagittal (x-y), z = 0", 2, (0, 1)), ("axial (x-z), y = 0", 1, (0, 2)),
            ("coronal (z-y), x = -depth/2", 0, (2, 1)))


def _section(ax, model: BreastModel, axis: int, dims: tuple[int, int], value: float, band: float) -> None:
    p = model.points
    cen = p[model.tets].mean(axis=1)
    sel = np.abs(cen[:, axis] - value) < band
    for reg, colour in ((1, "0.75"), (2, "tab:red")):
        m = sel & (model.region == reg)
        ax.scatter(cen[m, dims[0]], cen[m, dims[1]], s=2, c=colour, lw=0)
    sk = p[model.skin].mean(axis=1)
    ms = np.abs(sk[:, axis] - value) < band
    ax.scatter(sk[ms, dims[0]], sk[ms, dims[1]], s=3, c="tab:green", lw=0)
    fx = model.fixed & (np.abs(p[:, axis] - value) < band)
    ax.scatter(p[fx, dims[0]], p[fx, dims[1]], s=4, c="tab:blue", lw=0)
    n = p[model.nipple]
    ax.plot(n[dims[0]], n[dims[1]], "kx", ms=8)
    ax.set_aspect("equal")
    ax.set_xlabel("xyz"[dims[0]] + " (mm)")
    ax.set_ylabel("xyz"[dims[1]] + " (mm)")


def save_pictures(model: BreastModel, stem: str | Path) -> list[Path]:
    """Write ``<stem>_sections.png`` and ``<stem>_3d.png``; return their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stem = Path(stem)
    h = float(np.median(np.linalg.norm(model.points[model.tets[:, 0]] - model.points[model.tets[:, 1]], axis=1)))
    depth = float(model.points[:, 0].min())
    fig, axes = plt.subplots(1, 3, figsize=(15, 5))
    for ax, (title, axis, dims) in zip(axes, SECTIONS):
        _section(ax, model, axis, dims, depth / 2 if axis == 0 else 0.0, h)
        ax.set_title(title)
    fig.suptitle(f"{model.n_nodes} nodes, {model.n_tets} tets; grey tissue, red tumour, "
                 "green skin, blue fixed, x nipple")
    out = [stem.parent / f"{stem.name}_sections.png", stem.parent / f"{stem.name}_3d.png"]
    _io.save_figure(fig, out[0], dpi=80)
    fig = plt.figure(figsize=(7, 7))
    ax = fig.add_subplot(projection="3d")
    ax.plot_trisurf(model.points[:, 0], model.points[:, 1], model.points[:, 2], triangles=model.skin,
                    color="tan", alpha=0.35, lw=0)
    tum = model.points[np.unique(model.tets[model.region == 2])] if (model.region == 2).any() else np.zeros((0, 3))
    ax.scatter(*tum.T, s=1, c="tab:red")
    ax.scatter(*model.points[model.fixed].T, s=1, c="tab:blue")
    ax.set_xlabel("x anterior (mm)")
    ax.set_ylabel("y superior (mm)")
    ax.set_zlabel("z right (mm)")
    ax.set_box_aspect(np.ptp(model.points, axis=0))
    _io.save_figure(fig, out[1], dpi=80)
    return out
