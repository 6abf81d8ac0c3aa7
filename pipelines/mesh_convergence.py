"""Mesh convergence of a view's simulation: the same case meshed at several node counts.

Usage::

    .venv/bin/python pipelines/mesh_convergence.py CASE [--nodes 1800 3000 5000 10000]
        [--view cc] [--contact key=value ...] [--out DIR]

For each node target the case's MRI label map is meshed (``[model]`` of the case with
``target_nodes`` replaced), the view's shipped protocol runs at its defaults, and the
deformed model is projected to a virtual mammogram.  One markdown row per mesh:

* D reached, the upper-plate force (N) and the part of it carried within
  ``[contact] edge_band_mm`` of the plate's chest-wall edge (``edge``), and the rest
  (``body``);
* how far the tissue went behind the chest-wall plane (mm; the plane of the most
  posterior node, where the fixed nodes lie: a node behind it has been squeezed out past
  the plate edge);
* Newton iterations and wall seconds;
* against the finest mesh: the shift of the virtual nipple, the change of the
  tumour-centroid-to-nipple vector (what the registration's d_T measures), and the median
  distance of the breast contour from the finest one (mm).

A run that fails prints its error and the table goes on.  ``--out`` also writes the rows
as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from regtrack.config import config_from_assignments
from regtrack.errors import ConfigError
from regtrack.mechanics.contact import ContactConfig
from regtrack.mechanics.protocol import shipped_protocol
from regtrack.mechanics.run_view import run_protocol_on_model, summarise
from regtrack.virtual.project import project_model


def _contour_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Median distance (mm) of the points of contour ``a`` from the polyline ``b``."""
    from shapely.geometry import LineString, MultiPoint

    line = LineString(b)
    return float(np.median([line.distance(p) for p in MultiPoint(a).geoms]))


def run_one(case, labels, nodes: int, view: str, contact: ContactConfig) -> dict:
    from regtrack.model.build import build_model

    cfg = dataclasses.replace(case.config("model"), target_nodes=nodes)
    model = build_model(labels, scheme=case.mri.scheme, config=cfg, side=case.mri.side)
    row: dict = {"target_nodes": nodes, "nodes": model.n_nodes}
    t = time.perf_counter()
    try:
        res, timing = run_protocol_on_model(model, shipped_protocol(view), contact=contact)
    except Exception as exc:  # a failed mesh is a row of the table, not the end of it
        row["error"] = f"{type(exc).__name__}: {str(exc)[:200]}"
        return row
    sm = summarise(res, timing)
    x_cw = float(model.points[:, 0].min())  # the chest-wall plane: the most posterior node
    pos = model.points + res.u
    vm = project_model(model, pos, view=view.upper()).view
    tum = vm.tumour_contours[0].mean(axis=0) if vm.tumour_contours else None
    row.update(D=sm["D"], force_N=sm["upper_force_N"], edge_force_N=sm["upper_edge_force_N"],
               behind_wall_mm=max(0.0, float(x_cw - pos[:, 0].min())), iterations=sm["iterations"],
               wall_s=time.perf_counter() - t, nipple=vm.nipple.tolist(),
               tumour=None if tum is None else tum.tolist(), contour=vm.breast_contour.tolist())
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", type=Path)
    ap.add_argument("--nodes", nargs="+", type=int, default=[1800, 3000, 5000, 10000])
    ap.add_argument("--view", default="cc", choices=["cc", "mlo"])
    ap.add_argument("--contact", nargs="*", default=[], help="ContactConfig overrides key=value")
    ap.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from regtrack.case import load_case
    from regtrack.imaging.readers import read_label_map

    case = load_case(args.case, deep=False)
    labels = read_label_map(case.mri.labels)
    try:
        contact = config_from_assignments(ContactConfig, args.contact, where="--contact")
    except ConfigError as exc:
        ap.error(str(exc))
    rows = []
    for n in sorted(args.nodes):
        rows.append(run_one(case, labels, n, args.view, contact))
        print(f"meshed and ran {rows[-1]['nodes']} nodes", flush=True)
    ok = [r for r in rows if "error" not in r]
    ref = ok[-1] if ok else None
    print(f"\n{args.case.name} {args.view.upper()}, against the finest mesh "
          f"({ref['nodes'] if ref else '-'} nodes):\n")
    print("| nodes | D | force N | edge N | body N | behind wall mm | iter. | wall s "
          "| nipple shift mm | tumour-nipple change mm | contour median mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['nodes']} | failed: {r['error']} |")
            continue
        nip, rn = np.asarray(r["nipple"]), np.asarray(ref["nipple"])
        tn = (np.linalg.norm((np.asarray(r["tumour"]) - nip) - (np.asarray(ref["tumour"]) - rn))
              if r["tumour"] is not None and ref["tumour"] is not None else float("nan"))
        cd = _contour_distance(np.asarray(r["contour"]) - nip, np.asarray(ref["contour"]) - rn)
        print(f"| {r['nodes']} | {r['D']:.3f} | {r['force_N']:.1f} | {r['edge_force_N']:.1f} "
              f"| {r['force_N'] - r['edge_force_N']:.1f} | {r['behind_wall_mm']:.1f} "
              f"| {r['iterations']} | {r['wall_s']:.0f} | {np.linalg.norm(nip - rn):.2f} "
              f"| {tn:.2f} | {cd:.2f} |")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"mesh_convergence_{args.view}.json").write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
