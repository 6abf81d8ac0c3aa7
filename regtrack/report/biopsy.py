"""The biopsy section of the report: the needle target in an MR biopsy coil (issue 55).

``regtrack track CASE --view biopsy --mri-point X Y Z`` (or ``--landmarks``) writes
``biopsy.pdf`` (:func:`write_biopsy_report`), two A4 pages drawn by the report machinery
(:func:`regtrack.report.pdf.write_pdf`):

1. **the target**: two sections of the compressed breast through the predicted lesion
   position, in the plate frame (``e_x`` chest wall to nipple, ``n`` the plate normal,
   lateral to medial, ``e_down``; :func:`regtrack.virtual.frames.plate_frame`): the skin
   and the tumour outline before (the prone MRI, dashed) and after the compression
   (solid), the two plates as lines, the lesion's MRI position and its predicted
   compressed position with circles of 1 and 2 sigma when ``--uncertainty`` was given,
   and the needle path through the lateral plate (the grid plate of the coil, Azar et al.
   2000).  Below, the table of the targets: compressed position in the plate frame and in
   LPS mm, the displacement and the uncertainty;
2. **the protocol**: the compression sequence (the breast between the plates after each
   step) and, per step, D, the plate gap, the force on each plate and the force balance
   of the solver.

A point's plate-frame coordinates are ``s = (p - o) . e_x``, ``t = (p - o) . e_down`` and
its depth below the lateral plate ``d = (p - o) . n - h_lat`` with ``h_lat`` the lateral
plate's height along ``n`` (mm): ``(s, t)`` locate the needle on the grid, ``d`` is the
insertion depth from the plate face.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from regtrack.report import pages as P
from regtrack.report.fmt import drop_empty_columns, num

#: the biopsy protocol's plates (``biopsy.toml``): lower = lateral, fixed; upper = medial
PLATE_NAMES = {"lower": "lateral", "upper": "medial"}
SKIN, TUMOUR, TARGET, PLATE, NEEDLE = "#b07050", "tab:red", "tab:red", "#3050a0", "tab:green"


def plane_section(points: np.ndarray, tris: np.ndarray, origin: np.ndarray,
                  normal: np.ndarray) -> np.ndarray:
    """(K, 2, 3) segments where the triangles ``points[tris]`` cross the plane through
    ``origin`` with unit ``normal`` (mm): each crossed triangle gives the segment between
    the points of its two edges whose end heights ``h = (x - o) . n`` change sign,
    ``x = a + h_a / (h_a - h_b) (b - a)``."""
    tri = np.asarray(points, float)[np.asarray(tris, np.int64)]
    h = (tri - origin) @ normal
    segs = []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        ha, hb = h[:, i], h[:, j]
        cross = (ha > 0) != (hb > 0)
        t = np.where(cross, ha / np.where(cross, ha - hb, 1.0), np.nan)
        segs.append(tri[:, i] + t[:, None] * (tri[:, j] - tri[:, i]))
    segs = np.stack(segs, axis=1)  # (T, 3 edges, 3)
    ok = np.isfinite(segs[..., 0])
    two = ok.sum(axis=1) == 2
    return np.stack([s[o] for s, o in zip(segs[two], ok[two])]) if two.any() \
        else np.zeros((0, 2, 3))


def tumour_surface(model) -> np.ndarray:
    """(F, 3) boundary triangles of the tumour tetrahedra (faces used by one tumour tet)."""
    from regtrack.virtual.surface import boundary_faces

    return boundary_faces(np.asarray(model.tets)[np.asarray(model.region) == 2], model.points)


class PlateFrame:
    """The plate frame of a simulation (``result.json``'s ``plate_frame``), model frame mm."""

    def __init__(self, frame: dict, plates: dict):
        self.origin = np.asarray(frame["origin_mm"], float)
        self.e_x = np.asarray(frame["e_x"], float)
        self.e_down = np.asarray(frame["e_down"], float)
        self.n = np.asarray(frame["normal"], float)
        self.plates = plates
        #: each plate's face height along n (mm)
        self.h = {k: float((np.asarray(p["origin_mm"], float) - self.origin) @ self.n)
                  for k, p in plates.items()}

    def coords(self, x_model: np.ndarray) -> np.ndarray:
        """(M, 3) model-frame points -> (s, t, h): along e_x, e_down and n (mm)."""
        d = np.atleast_2d(x_model) - self.origin
        return np.stack([d @ self.e_x, d @ self.e_down, d @ self.n], axis=-1)

    def depth(self, x_model: np.ndarray) -> np.ndarray:
        """(M,) depth below the lateral (lower) plate's face along n (mm)."""
        return self.coords(x_model)[:, 2] - self.h.get("lower", np.nan)


def _section_lines(ax, points, tris, frame: PlateFrame, through: np.ndarray, cut: np.ndarray,
                   axes_of: tuple[int, int], **style) -> None:
    from matplotlib.collections import LineCollection

    seg = plane_section(points, tris, through, cut)
    if len(seg):
        uv = frame.coords(seg.reshape(-1, 3))[:, list(axes_of)].reshape(-1, 2, 2)
        ax.add_collection(LineCollection(uv, **style))


def draw_target_section(ax, state, targets, frame: PlateFrame, *, cut: str) -> None:
    """A section of the compressed breast through the first target, in the plate frame.

    ``cut="axial"``: the plane normal to ``e_down`` (axes ``e_x``, ``n``); ``"coronal"``:
    normal to ``e_x`` (axes ``e_down``, ``n``).  ``targets``: ``(name, MRI model-frame
    point, compressed model-frame point, sigma mm or None)``.
    """
    from matplotlib.patches import Circle

    model, dmap = state.model, state.dmap
    normal, a = (frame.e_down, 0) if cut == "axial" else (frame.e_x, 1)
    axes_of = (a, 2)
    _, mri0, comp0, _ = targets[0]
    tum = tumour_surface(model)
    for pts, through, ls, lw in ((dmap.reference, mri0, "--", 0.9),
                                 (dmap.deformed, comp0, "-", 1.4)):
        _section_lines(ax, pts, model.skin, frame, through, normal, axes_of, colors=SKIN,
                       linestyles=ls, linewidths=lw)
        _section_lines(ax, pts, tum, frame, through, normal, axes_of, colors=TUMOUR,
                       linestyles=ls, linewidths=lw * 0.8)
    from regtrack.mechanics.pictures import plate_opening, plate_outline

    lo, hi = ax.dataLim.intervalx if ax.dataLim.width > 0 else (-50.0, 50.0)
    for name, h in frame.h.items():
        if cut == "axial":  # the plate face with its rounded chest-wall edge
            line = plate_outline(frame.plates[name], frame.e_x, frame.n, hi + 10, opening=True)
            line[:, 0] -= frame.origin @ frame.e_x
            line[:, 1] -= frame.origin @ frame.n
        else:  # the plates extend beyond the breast along e_down
            line = np.array([[lo - 10, h], [hi + 10, h]])
            gap = plate_opening(frame.plates[name], frame.e_down)
            if gap is not None:  # the section crosses the opening
                g0, g1 = (v - frame.origin @ frame.e_down for v in gap)
                line = np.array([[lo - 10, h], [g0, h], [np.nan, np.nan], [g1, h], [hi + 10, h]])
        ax.plot(*line.T, color=PLATE, lw=2.2, solid_capstyle="butt")
        ax.text(hi + 10, h, f"{PLATE_NAMES.get(name, name)} plate ", fontsize=6.5,
                color=PLATE, va="top" if name == "lower" else "bottom", ha="right")
    for k, (_name, mri, comp, sigma) in enumerate(targets):
        m, c = frame.coords(mri)[0], frame.coords(comp)[0]
        ax.annotate("", xy=(c[a], c[2]), xytext=(m[a], m[2]),
                    arrowprops=dict(arrowstyle="->", color="0.3", lw=0.8))
        ax.plot(m[a], m[2], "o", mfc="none", mec=TARGET, ms=6)
        ax.plot(c[a], c[2], "+", color=TARGET, ms=11, mew=2)
        if sigma is not None:
            for j in (1, 2):
                ax.add_patch(Circle((c[a], c[2]), j * sigma, fill=False, color=TARGET, lw=0.8,
                                    ls="-" if j == 1 else ":"))
        if k == 0 and "lower" in frame.h:
            ax.plot([c[a], c[a]], [frame.h["lower"], c[2]], color=NEEDLE, lw=1.4, ls=(0, (4, 2)))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel(("chest wall → nipple, along e_x (mm)" if cut == "axial"
                   else "along e_down (mm)"), fontsize=7.5)
    ax.set_ylabel("lateral → medial, along the plate normal (mm)", fontsize=7.5)
    ax.tick_params(labelsize=7)
    what = "normal to e_down" if cut == "axial" else "normal to e_x"
    ax.set_title(f"section {what} through the target", fontsize=8.5)


def section_legend(fig, *, y: float, sigma: bool = True) -> None:
    """One legend, in two rows, for the two :func:`draw_target_section` panels."""
    from matplotlib.lines import Line2D

    items = [(Line2D([], [], color=SKIN, ls="--"), "skin, MRI (prone)"),
             (Line2D([], [], color=TUMOUR, ls="--"), "tumour, MRI"),
             (Line2D([], [], ls="", marker="o", mfc="none", mec=TARGET), "lesion in the MRI"),
             (Line2D([], [], color=PLATE, lw=2.2), "plates"),
             (Line2D([], [], color=SKIN), "skin, compressed"),
             (Line2D([], [], color=TUMOUR), "tumour, compressed"),
             (Line2D([], [], ls="", marker="+", color=TARGET, mew=2),
              "predicted target" + (" (circles: 1σ, 2σ)" if sigma else "")),
             (Line2D([], [], color=NEEDLE, ls=(0, (4, 2))), "needle through the lateral plate")]
    fig.legend(*zip(*items), loc="upper center", ncol=4, fontsize=7, frameon=False,
               bbox_to_anchor=(0.5, y))


def target_cells(state, mapped, frame: PlateFrame) -> tuple[list[str], list[list[str]]]:
    """Per tracked point: name, MRI and compressed LPS (mm), plate-frame (s, t, depth),
    displacement and 1-sigma (mm)."""
    head = ["Point", "MRI\nLPS (mm)", "Compressed\nLPS (mm)", "Plate frame\ns, t (mm)",
            "Depth below the\nlateral plate (mm)", "Moved\n(mm)", "1σ\n(mm)"]
    rows = []
    for r in (r for m in mapped for r in m.rows()):
        comp = np.asarray(r["compressed_lps_mm"], float)
        c = state.dmap.frame.to_model(comp[None])
        st = frame.coords(c)[0]
        name = r["name"] + ("" if r["direction"] == "mri->compressed"
                            else "\n(given compressed)")
        rows.append([name, _xyz(r["mri_lps_mm"]), _xyz(comp), f"{num(st[0], 1)}, {num(st[1], 1)}",
                     num(frame.depth(c)[0], 1), num(r["displacement_mm"], 1),
                     num(r.get("sigma_mm"), 1)])
    return drop_empty_columns(head, rows)


def _xyz(p) -> str:
    return ", ".join(num(v, 1) for v in p)


def protocol_cells(state) -> tuple[list[str], list[list[str]]]:
    """Per simulation step: D, plate gap, the force on each plate (N) and the force balance
    (imbalance over load, against the solver's tolerance)."""
    head = ["Step", "D (%)", "Plate gap\n(mm)", "Lateral plate\nforce (N)",
            "Medial plate\nforce (N)", "Force\nimbalance (N)", "Load (N)",
            "Imbalance / load\n(tolerance)"]
    rows = []
    for s in state.sim.steps:
        c = s.get("contact") or {}
        fb = (s.get("solver") or {}).get("force_balance") or {}
        ok = fb.get("ok")
        rel = fb.get("relative")
        balance = "–" if rel is None else (f"{num(100 * rel, 3)} % ({num(100 * fb['tol'], 1)} %)"
                                          f" {'✓' if ok else '✗'}")
        rows.append([str(s.get("name", "")).replace("-", " "),
                     num(None if s.get("D") is None else 100 * s["D"], 1),
                     num(s.get("plate_gap_mm"), 1),
                     num((c.get("lower") or {}).get("normal_force_N"), 2),
                     num((c.get("upper") or {}).get("normal_force_N"), 2),
                     num(fb.get("imbalance_N"), 4), num(fb.get("load_N"), 2), balance])
    return drop_empty_columns(head, rows)


def _frame_of(state) -> tuple[dict, list[dict]]:
    doc = json.loads((Path(state.sim.folder) / "result.json").read_text())
    return doc["plate_frame"], doc["steps"]


def opening_line(frame: PlateFrame, name: str) -> str:
    """One line locating a plate's opening (the grid's compression window) in the plate frame."""
    from regtrack.mechanics.pictures import plate_opening

    (s0, s1), (t0, t1) = ((lo - frame.origin @ ax, hi - frame.origin @ ax) for ax in
                          (frame.e_x, frame.e_down)
                          for lo, hi in [plate_opening(frame.plates[name], ax)])
    return (f"Opening in the {PLATE_NAMES.get(name, name)} plate: {num(s1 - s0, 0)} x "
            f"{num(t1 - t0, 0)} mm, s {num(s0, 1)} to {num(s1, 1)} mm, t {num(t0, 1)} to "
            f"{num(t1, 1)} mm (the skin over it is free)")


def target_page(state, mapped, case_id: str) -> Callable:
    """The drawing function of the target page (see the module docstring)."""
    frame_doc, steps = _frame_of(state)
    frame = PlateFrame(frame_doc, steps[-1]["plates"])
    fwd = [m for m in mapped if m.direction == "mri->compressed"]
    to_model = state.dmap.frame.to_model
    sig = lambda m, i: None if m.sigma_mm is None else float(m.sigma_mm[i])  # noqa: E731
    targets = [(n, to_model(m.given_lps_mm[i][None]), to_model(m.mapped_lps_mm[i][None]),
                sig(m, i)) for m in fwd for i, n in enumerate(m.names)]
    summary = state.summary

    def draw(fig) -> None:
        P.title(fig, f"MR-guided biopsy: needle target, case {case_id}")
        lines = [f"{summary.get('protocol', 'biopsy')} protocol: D = "
                 f"{num(100 * (summary.get('D') or 0), 1)} % of T0 = "
                 f"{num(summary.get('T0_mm'), 1)} mm, plate gap "
                 f"{num(summary.get('plate_gap_mm'), 1)} mm, lateral plate "
                 f"{num(summary.get('lower_force_N'), 1)} N, medial plate "
                 f"{num(summary.get('upper_force_N'), 1)} N",
                 "Frame: plate frame (s along e_x, chest wall → nipple; t along e_down; depth "
                 "from the lateral plate face along the plate normal) and patient LPS (the "
                 "MRI's frame of reference)."]
        lines += [opening_line(frame, name) for name in frame.plates
                  if frame.plates[name].get("window_mm")]
        import textwrap

        body = [w for ln in lines for w in textwrap.wrap(ln, 120)]
        fig.text(0.05, 0.94, "\n".join(body), fontsize=8, color="0.25", va="top",
                 linespacing=1.5)
        if targets:
            ax0 = fig.add_axes([0.08, 0.47, 0.4, 0.38])
            ax1 = fig.add_axes([0.57, 0.47, 0.4, 0.38])
            draw_target_section(ax0, state, targets, frame, cut="axial")
            draw_target_section(ax1, state, targets, frame, cut="coronal")
            section_legend(fig, y=0.435, sigma=any(t[3] is not None for t in targets))
        head, rows = target_cells(state, mapped, frame)
        fig.text(0.05, 0.365, "Targets", fontsize=10, weight="bold", va="top")
        h = 0.026 * (len(rows) + 1.5)
        P.table(fig.add_axes([0.05, 0.345 - h, 0.9, h]), head, rows, fontsize=7.5,
                col_widths=[0.18, 0.17, 0.17, 0.13, 0.15, 0.1, 0.1][:len(head)])
        note = ("Sections: the prone MRI shape (dashed) is cut through the lesion's MRI "
                "position, the compressed one (solid) through its predicted position. 1σ: "
                "from c1, ν and the plate position (--uncertainty), else not computed. The "
                "needle enters perpendicular to the lateral plate at (s, t) and reaches the "
                "target at the given depth.")
        if any("surrogate" in (m.sigma_sources or {}).values() for m in mapped):
            note += (" The 1σ terms are predicted by the per-patient surrogate (points_*.json: "
                     "its held-out error); the positions are the full simulation's.")

        fig.text(0.05, 0.325 - h, "\n".join(textwrap.wrap(note, 140)), fontsize=6.5,
                 color="0.3", va="top")

    return draw


def protocol_page(state, states: list[tuple[str, np.ndarray]]) -> Callable:
    """The drawing function of the protocol page: sequence panels (``states``: step name and
    displacement (N, 3) mm after each step) and the steps table."""
    from regtrack.mechanics.pictures import draw_sequence
    from regtrack.model.checks import cut_faces

    frame_doc, steps = _frame_of(state)
    model = state.model

    def draw(fig) -> None:
        P.title(fig, f"Biopsy compression: {state.summary.get('protocol', 'biopsy')} protocol")
        k = len(states)
        if k:
            w = 0.9 / k
            axes = [fig.add_axes([0.07 + j * w, 0.6, w - 0.04, 0.3]) for j in range(k)]
            draw_sequence(axes, model.points, model.skin, steps[:k], [u for _, u in states],
                          frame_doc, cut_faces(model.tets, model.skin, model.fixed))
            P.same_limits(axes)
            for a in axes:
                a.set_xlabel("chest wall → nipple (mm)", fontsize=7)
            axes[0].set_ylabel("lateral → medial (mm)", fontsize=7)
        head, rows = protocol_cells(state)
        fig.text(0.05, 0.53, "Steps", fontsize=10, weight="bold", va="top")
        h = 0.03 * (len(rows) + 1.5)
        P.table(fig.add_axes([0.05, 0.51 - h, 0.9, h]), head, rows, fontsize=7.5,
                col_widths=[0.18, 0.08, 0.1, 0.11, 0.11, 0.11, 0.09, 0.22]
                if len(head) == 8 else None)
        s = state.summary
        note = (f"D: relative reduction of the breast thickness T0 = {num(s.get('T0_mm'), 1)} mm "
                "between the plates. Force balance: the plates' and the chest wall's reactions "
                "against the load, relative to the load, with the solver's tolerance. "
                f"Maximum penetration {num(s.get('max_penetration_mm'), 3)} mm; "
                f"{s.get('increments', '–')} load increments, {s.get('iterations', '–')} "
                "Newton iterations.")
        import textwrap

        fig.text(0.05, 0.49 - h, "\n".join(textwrap.wrap(note, 140)), fontsize=6.5,
                 color="0.3", va="top")

    return draw


def write_biopsy_report(path: str | Path, state, mapped, *, case_id: str,
                        states: list[tuple[str, np.ndarray]]) -> Path:
    """``biopsy.pdf``: the target page and the protocol page (:mod:`regtrack.report.pdf`);
    ``states`` as for :func:`protocol_page`."""
    from regtrack.report.pdf import CaseReport, write_pdf

    rep = CaseReport(case_id, extra_pages=[target_page(state, mapped, case_id),
                                           protocol_page(state, states)])
    return write_pdf(rep, path)
