"""Pictures of a protocol run: the breast between the plates after each step.

One PNG with a panel per protocol step (like Figure 4 of Lapuebla-Ferri et al.): the
skin of the deformed breast projected on the plane spanned by the plate's
posterior->anterior axis ``e_x`` and its normal ``n`` (a side view of the plates), with
both plate faces and their rounded chest-wall edges drawn at their positions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regtrack._io import atomic_path


def plate_outline(plate: dict, e_x: np.ndarray, n: np.ndarray, x_max: float) -> np.ndarray:
    """Side-view polyline (mm) of a plate face with its rounded chest-wall edge."""
    o = np.asarray(plate["origin_mm"], float)
    N = np.asarray(plate["normal"], float)
    r = float(plate["edge_radius_mm"])
    s0 = float(plate["s_range_mm"][0]) if not isinstance(plate["s_range_mm"][0], str) else -1e3
    up = float(N @ n)  # +1 lower plate (faces +n), -1 upper plate
    h0 = float(o @ n)
    ang = np.linspace(0.0, np.pi / 2, 20)
    arc_x = s0 - r * np.sin(ang)
    arc_h = h0 - up * r * (1 - np.cos(ang))
    x = np.concatenate([[x_max], arc_x])
    h = np.concatenate([[h0], arc_h])
    return np.column_stack([x, h])


def protocol_figure(path: str | Path, points: np.ndarray, skin: np.ndarray, steps: list,
                    plate_frame: dict, *, title: str = "") -> Path:
    """Write the step sequence PNG.

    Parameters
    ----------
    path : output PNG.
    points : (N, 3) reference coordinates (mm).
    skin : (S, 3) skin triangles.
    steps : list of :class:`~regtrack.mechanics.protocol_run.StepRecord`.
    plate_frame : ``PlateFrame.to_dict()`` of the view.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    e_x = np.asarray(plate_frame["e_x"], float)
    n = np.asarray(plate_frame["normal"], float)
    k = len(steps)
    fig, axes = plt.subplots(1, k, figsize=(3.2 * k, 3.6), squeeze=False, sharex=True, sharey=True)
    xs = [(points + s.u) @ e_x for s in steps]
    x_max = max(float(x.max()) for x in xs) + 10
    for ax, st in zip(axes[0], steps):
        x = points + st.u
        poly = np.stack([x[skin] @ e_x, x[skin] @ n], axis=-1)
        ax.add_collection(PolyCollection(poly, facecolors="#f3c6a5", edgecolors="#b07050",
                                         linewidths=0.1, alpha=0.6))
        for name, pl in st.plates.items():
            line = plate_outline(pl, e_x, n, x_max)
            ax.plot(line[:, 0], line[:, 1], color="#3050a0", lw=1.5)
        lab = st.name + (f"\nD = {100 * st.D:.1f} %" if st.D is not None else "")
        ax.set_title(lab, fontsize=8)
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlabel("posterior -> anterior (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
    axes[0][0].set_ylabel("along plate normal (mm)", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return Path(path)
