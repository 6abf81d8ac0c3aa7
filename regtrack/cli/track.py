"""regtrack track CASE: where is a lesion of one image in the others?

Examples::

    regtrack track sample_cases/phantom01 --label tumour
    regtrack track CASE --mri-point -109.7 0.3 10.3          # LPS mm
    regtrack track CASE --cc-point 1510 2210                  # DICOM (row, col) on the CC
    regtrack track CASE --mlo-point 1800 2000 --label tumour  # curve on the CC + most likely point
    regtrack track CASE --cc-contour mammo/cc_tumour.json     # region on the MLO

The mesh and the simulations come from the stage cache of ``regtrack run`` (same
``--cache``); when they are missing they are run first (minutes, with progress
messages) unless ``--no-simulate`` is given, which stops with an error instead.
Writes ``tracking.json``, ``track_cc.png``/``track_mlo.png`` and ``tracking.pdf``.
"""

from __future__ import annotations

import argparse

HELP = "predict where an MRI point/region or a point on one mammogram lies in the other images"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("case", help="case folder (holding case.toml) or the case.toml itself")
    p.add_argument("--mri-point", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="MRI point in the patient frame (LPS, mm)")
    p.add_argument("--label", metavar="LABEL",
                   help="'tumour' (every tumour of the model), 'tumour:K', or a label value of "
                        "the MRI label map (its voxels are tracked by their centroid)")
    p.add_argument("--cc-point", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="point on the real CC mammogram, (row, col) of the DICOM pixel grid: "
                        "predicted as a curve on the MLO")
    p.add_argument("--mlo-point", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="point on the real MLO mammogram (DICOM row, col): a curve on the CC")
    p.add_argument("--cc-contour", metavar="JSON",
                   help='contour marked on the real CC ({"points_rc": [[row, col], ...]}, the '
                        "tumour annotation format): its region on the MLO")
    p.add_argument("--mlo-contour", metavar="JSON", help="the same for a contour on the MLO")
    p.add_argument("--views", default=None, help="comma-separated views (default: all in the case)")
    p.add_argument("--out", default=None, help="output folder (default: reports/<case id>/track)")
    p.add_argument("--cache", default=None,
                   help="stage cache of `regtrack run` (default: .regtrack-cache)")
    p.add_argument("--no-simulate", action="store_true",
                   help="fail instead of running a mesh/simulation missing from the cache")
    p.add_argument("--ray-step", type=float, default=None, metavar="MM",
                   help="sampling of the projection ray for --cc-point/--mlo-point "
                        "(mm, default 0.25)")
    p.add_argument("--no-pdf", action="store_true", help="JSON and PNG overlays only")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import logging
    import time
    from pathlib import Path

    from rich.console import Console

    from regtrack.case import load_case
    from regtrack.errors import TrackingError
    from regtrack.tracking.config import TrackingConfig
    from regtrack.tracking.figures import summary_lines, write_outputs
    from regtrack.tracking.session import open_case
    from regtrack.tracking.track import track_case

    console = Console(stderr=True)
    if args.mri_point is not None and args.label is not None:
        raise TrackingError("give either --mri-point or --label, not both")
    if args.ray_step is not None and not 0 < args.ray_step <= 5:
        raise TrackingError(f"--ray-step {args.ray_step}: must be in (0, 5] mm")
    case = load_case(args.case, deep=False)
    out = Path(args.out) if args.out else Path("reports") / case.id / "track"
    views = tuple(v.strip().upper() for v in args.views.split(",")) if args.views else None
    points = {}
    if args.cc_point is not None:
        points["CC"] = tuple(args.cc_point)
    if args.mlo_point is not None:
        points["MLO"] = tuple(args.mlo_point)
    contours = {}
    for v, f in (("CC", args.cc_contour), ("MLO", args.mlo_contour)):
        if f is not None:
            from regtrack.case.annotations import read_tumour_polygons

            contours[v] = read_tumour_polygons(f)[0]
    if views is not None:
        for v in [*points, *contours]:
            other = "MLO" if v == "CC" else "CC"
            if v not in views or other not in views:
                raise TrackingError(f"--{v.lower()}-point needs both CC and MLO in --views")
    cfg = TrackingConfig()
    if args.ray_step is not None:
        cfg = dataclasses.replace(cfg, ray_step_mm=args.ray_step)
    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        console.print(f"[dim]{time.perf_counter() - t0:7.1f} s[/dim]  {msg}")

    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        logging.getLogger("regtrack").setLevel(logging.WARNING)
    with console.status("preparing the case (cached stages are re-used)"):
        session = open_case(args.case, views=views, cache_dir=args.cache,
                            simulate=not args.no_simulate, config=cfg, progress=progress)
        result = track_case(session, mri_point=args.mri_point, label=args.label,
                            view_points=points, view_contours=contours)
    reals = {v: vm.real for v, vm in session.views.items()}
    paths = write_outputs(result, out, reals=reals, pdf=not args.no_pdf)
    for line in summary_lines(result):
        console.print(line, highlight=False)
    dt = time.perf_counter() - t0
    console.print(f"tracking written to {out} ({len(paths)} files, {dt:.1f} s)")
    return 0
