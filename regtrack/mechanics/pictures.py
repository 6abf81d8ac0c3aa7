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


def plate_outline(plate: dict, e_x: np.ndarray, n: np.ndarray, x_max: float, *,
                  opening: bool = False) -> np.ndarray:
    """Side-view polyline (mm) of a plate face with its rounded chest-wall edge; with
    ``opening``, broken (a NaN row) where the face has its opening (a section through it)."""
    o = np.asarray(plate["origin_mm"], float)
    N = np.asarray(plate["normal"], float)
    r = float(plate["edge_radius_mm"])
    s0 = float(plate["s_range_mm"][0]) if not isinstance(plate["s_range_mm"][0], str) else -1e3
    up = float(N @ n)  # +1 lower plate (faces +n), -1 upper plate
    h0 = float(o @ n)
    ang = np.linspace(0.0, np.pi / 2, 20)
    arc_x = s0 - r * np.sin(ang)
    arc_h = h0 - up * r * (1 - np.cos(ang))
    face_x, face_h = [x_max], [h0]
    gap = plate_opening(plate, e_x) if opening else None
    if gap is not None and gap[0] < x_max:
        face_x += [min(gap[1], x_max), np.nan, gap[0]]
        face_h += [h0, np.nan, h0]
    return np.column_stack([np.concatenate([face_x, arc_x]), np.concatenate([face_h, arc_h])])


def plate_opening(plate: dict, axis: np.ndarray) -> tuple[float, float] | None:
    """Extent ``(lo, hi)`` along the model-frame unit vector ``axis`` (mm) of a plate's
    opening (:attr:`.plates.RigidPlate.window`), from its record; None for a solid plate."""
    w = plate.get("window_mm")
    if not w:
        return None
    o, N, e1 = (np.asarray(plate[k], float) for k in ("origin_mm", "normal", "e1"))
    e2 = np.cross(N, e1)
    proj = [(o + s * e1 + t * e2) @ np.asarray(axis, float) for s in w[:2] for t in w[2:]]
    return float(min(proj)), float(max(proj))


#: fill colours of the sequence panels: skin, and the faces where the MRI's field of view
#: cut the breast (no skin there)
SKIN_FILL, CUT_FILL = "#f3c6a5", "#c8c8c8"


def draw_sequence(axes, points: np.ndarray, skin: np.ndarray, steps: list[dict],
                  states: list[np.ndarray], plate_frame: dict, cut: np.ndarray | None = None) -> None:
    """The breast between the plates after each step, one panel per step: the outer surface
    projected on the plane of the plate's posterior->anterior axis ``e_x`` and its normal
    ``n`` (a side view of the plates, as Figure 4 of Lapuebla-Ferri et al.), with the plate
    faces and their rounded chest-wall edges at their positions.

    ``steps``: per step a dict with ``name``, ``D`` and ``plates`` (the plate records of the
    result JSON); ``states``: the displacement (N, 3) mm of each step, model frame;
    ``cut``: the outer faces cut by the MRI's field of view (:func:`regtrack.model.checks.
    cut_faces`), drawn grey when the view looks across them (their projected area is more
    than 1 % of the skin's), else they would show as holes.
    """
    from matplotlib.collections import PolyCollection

    e_x = np.asarray(plate_frame["e_x"], float)
    n = np.asarray(plate_frame["normal"], float)
    x_max = max(float(((points + u) @ e_x).max()) for u in states) + 10
    layers = [(skin, SKIN_FILL)]
    if cut is not None and len(cut) and _area(points, cut, e_x, n) > 0.01 * _area(points, skin, e_x, n):
        layers.append((cut, CUT_FILL))  # seen across, not edge-on
    for ax, st, u in zip(axes, steps, states):
        x = points + u
        for tris, colour in layers:
            poly = np.stack([x[tris] @ e_x, x[tris] @ n], axis=-1)
            ax.add_collection(PolyCollection(poly, facecolors=colour, edgecolors="#b07050",
                                             linewidths=0.1, alpha=0.6))
        for pl in (st.get("plates") or {}).values():
            line = plate_outline(pl, e_x, n, x_max)
            ax.plot(line[:, 0], line[:, 1], color="#3050a0", lw=1.5)
        D = st.get("D")
        ax.set_title(str(st.get("name", "")).replace("-", " ")
                     + ("" if D is None else f"\nD = {100 * D:.1f} %"), fontsize=8)
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.tick_params(labelsize=6.5)
        ax.set_xlabel("chest wall → nipple (mm)", fontsize=7)
    axes[0].set_ylabel("along the plate normal (mm)", fontsize=7)
    if len(layers) > 1:
        axes[-1].annotate("grey: cut by the MRI's field of view (no skin)", (1.0, 0.0),
                          xycoords="axes fraction", xytext=(0, -24), textcoords="offset points",
                          fontsize=6, ha="right", va="top", color="0.35")


def _area(points: np.ndarray, tris: np.ndarray, e_x: np.ndarray, n: np.ndarray) -> float:
    """Summed area (mm^2) of the triangles projected on the plane of ``e_x`` and ``n``."""
    x, y = points[tris] @ e_x, points[tris] @ n
    return float(0.5 * np.abs((x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0])
                              - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])).sum())


def protocol_figure(path: str | Path, points: np.ndarray, skin: np.ndarray, steps: list,
                    plate_frame: dict, *, title: str = "", cut: np.ndarray | None = None) -> Path:
    """Write the step sequence PNG (:func:`draw_sequence`).

    Parameters
    ----------
    path : output PNG.
    points : (N, 3) reference coordinates (mm).
    skin : (S, 3) skin triangles.
    steps : list of :class:`~regtrack.mechanics.protocol_run.StepRecord`.
    plate_frame : ``PlateFrame.to_dict()`` of the view.
    cut : outer faces cut by the MRI's field of view (drawn grey).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = len(steps)
    fig, axes = plt.subplots(1, k, figsize=(3.2 * k, 3.6), squeeze=False, sharex=True, sharey=True)
    draw_sequence(list(axes[0]), points, skin, [{"name": s.name, "D": s.D, "plates": s.plates} for s in steps],
                  [s.u for s in steps], plate_frame, cut)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return Path(path)
