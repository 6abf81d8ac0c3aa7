"""regtrack track CASE: where is a lesion of one image in the others?

Examples::

    regtrack track sample_cases/phantom01 --label tumour
    regtrack track CASE --mri-point -109.7 0.3 10.3          # LPS mm
    regtrack track CASE --cc-point 1510 2210                  # DICOM (row, col) on the CC
    regtrack track CASE --mlo-point 1800 2000 --label tumour  # curve on the CC + most likely point
    regtrack track CASE --cc-contour mammo/cc_tumour.json     # region on the MLO
    regtrack track CASE --view biopsy --mri-point -109.7 0.3 10.3   # 3-D, in the compressed breast
    regtrack track CASE --view biopsy --landmarks points.mrk.json --warp
    regtrack track CASE --view cc --compressed-point -100 5 12      # compressed -> MRI

The mesh and the simulations come from the stage cache of ``regtrack run`` (same
``--cache``); when they are missing they are run first (minutes, with progress
messages) unless ``--no-simulate`` is given, which stops with an error instead.
Writes ``tracking.json``, ``track_cc.png``/``track_mlo.png`` and ``tracking.pdf``.

With ``--view cc|mlo|biopsy`` the tracking stays in 3-D (no mammogram is needed): MRI points
and landmark lists are mapped into that simulated compression, points of the compressed
breast back to the MRI, and ``--warp`` resamples the label map (and the MR series) into it
(:mod:`regtrack.tracking.compressed`); writes ``points_<view>.json/.csv``,
``labels_<view>.nii.gz`` / ``mri_<view>.nii.gz`` (for a DICOM input also the DICOM series
``labels_<view>/`` / ``mri_<view>/``, same study and frame of reference, pseudonymised
unless ``--keep-identifiers``) and, for ``--view biopsy`` with points,
``biopsy.pdf`` (the needle target and the protocol, :mod:`regtrack.report.biopsy`).
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
    g = p.add_argument_group("3-D tracking in one simulated compression (no mammogram needed)")
    g.add_argument("--view", type=str.upper, choices=["CC", "MLO", "BIOPSY"],
                   help="the compression: CC, MLO or BIOPSY (prone, latero-medial, MR biopsy "
                        "coil); --mri-point and --landmarks are mapped into it")
    g.add_argument("--landmarks", metavar="FILE",
                   help="MRI landmarks: CSV (name,x,y,z, LPS mm) or a 3D Slicer .mrk.json")
    g.add_argument("--compressed-point", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="point of the compressed breast (LPS mm, the MRI's frame) mapped back "
                        "to the MRI")
    g.add_argument("--uncertainty", action="store_true",
                   help="1-sigma of each mapped point from c1, nu and the plate position "
                        "([tracking] c1_rel_sigma, nu_sigma, degree_sigma): three more "
                        "simulations (cached)")
    g.add_argument("--surrogate", metavar="DIR",
                   help="with --uncertainty: predict the three perturbed compressions with this "
                        "view's surrogate (`regtrack surrogate build`) instead of simulating "
                        "them; the points stay the full simulation's")
    g.add_argument("--compare-mri", metavar="LABELS",
                   help="label map of the compressed MRI (the case's label scheme): distance "
                        "of the simulated skin to its breast surface (RMS, p95, mm)")
    g.add_argument("--compare-landmarks", metavar="FILE",
                   help="the --landmarks picked in the compressed MRI (same names, LPS mm): "
                        "distance of each simulated landmark")
    g.add_argument("--warp", action="store_true",
                   help="write the label map (and the MR series) warped into the compression "
                        "as NIfTI and, for a DICOM input, as a DICOM series in its frame of "
                        "reference")
    g.add_argument("--keep-identifiers", action="store_true",
                   help="the warped DICOM series keeps the patient's identifiers (default: "
                        "the DICOM PS3.15 basic profile with the case's pseudonym)")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from regtrack.cli._checks import existing_file, writable_folder
    from regtrack.errors import TrackingError

    console = Console(stderr=True)
    if args.mri_point is not None and args.label is not None:
        raise TrackingError("give either --mri-point or --label, not both")
    if args.ray_step is not None and not 0 < args.ray_step <= 5:  # also refuses NaN
        raise TrackingError(f"--ray-step {args.ray_step}: must be in (0, 5] mm")
    _check_numbers(args)
    if (args.view is not None or args.landmarks or args.compressed_point or args.warp
            or args.compare_mri or args.compare_landmarks or args.uncertainty):
        return _track_3d(args, console)
    existing_file(args.cc_contour, "--cc-contour", "contour JSON")
    existing_file(args.mlo_contour, "--mlo-contour", "contour JSON")
    writable_folder(args.out, "--out")
    writable_folder(args.cache, "--cache")
    if not any(x is not None for x in (args.mri_point, args.label, args.cc_point, args.mlo_point,
                                       args.cc_contour, args.mlo_contour)):
        raise TrackingError("nothing to track: give --mri-point, --label, --cc-point, "
                            "--mlo-point, --cc-contour or --mlo-contour")
    from regtrack.privacy import identifiers_of_case_folder, pseudonymous_id, scrub_logs

    found = identifiers_of_case_folder(args.case)  # as `regtrack run`: no identifier in outputs
    with scrub_logs(found):
        return _track(args, console, found, pseudonymous_id)


def _track(args: argparse.Namespace, console, found, pseudonymous_id) -> int:
    import dataclasses
    import logging
    import time
    from pathlib import Path

    from regtrack.case import load_case
    from regtrack.cli._checks import writable_folder
    from regtrack.errors import TrackingError
    from regtrack.tracking.config import TrackingConfig
    from regtrack.tracking.figures import summary_lines, write_outputs
    from regtrack.tracking.session import open_case
    from regtrack.tracking.track import track_case

    case = load_case(args.case, deep=False)
    case_id = pseudonymous_id(case.id, found)
    out = Path(args.out) if args.out else Path("reports") / case_id / "track"
    writable_folder(out, "--out")
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
        unknown = [v for v in views if v not in ("CC", "MLO")]
        if unknown:
            raise TrackingError(f"--views: unknown view {unknown[0]!r}; use CC and/or MLO")
        for v in [*points, *contours]:
            other = "MLO" if v == "CC" else "CC"
            if v not in views or other not in views:
                kind = "point" if v in points else "contour"
                raise TrackingError(f"--{v.lower()}-{kind} needs both CC and MLO in --views")
    for v in [*points, *contours]:  # before any mesh, simulation or registration runs
        if v not in case.views:
            have = ", ".join(case.views) or "none"
            raise TrackingError(f"--{v.lower()}-{'point' if v in points else 'contour'}: the case "
                                f"has no [views.{v}] mammogram (views: {have}); add one to "
                                "case.toml")
        other = "MLO" if v == "CC" else "CC"
        if other not in case.views and views is None:
            raise TrackingError(f"--{v.lower()}-{'point' if v in points else 'contour'}: needs "
                                f"the {other} view too; add [views.{other}] to case.toml")
    if points or contours:
        _check_on_image(case, points, contours)
    if args.label is not None:
        _check_label(case, args.label)
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
    result = dataclasses.replace(result, case_id=case_id,
                                 notes=[found.scrub(n) for n in result.notes])
    reals = {v: vm.real for v, vm in session.views.items()}
    paths = write_outputs(result, out, reals=reals, pdf=not args.no_pdf)
    for line in summary_lines(result):
        console.print(line, highlight=False)
    dt = time.perf_counter() - t0
    console.print(f"tracking written to {out} ({len(paths)} files, {dt:.1f} s)")
    return 0


def _track_3d(args: argparse.Namespace, console) -> int:
    """``--view``: points and the warped MRI in one simulated compression (3-D only)."""
    import logging
    import time
    from pathlib import Path

    from regtrack.cli._checks import existing_file, writable_folder
    from regtrack.errors import TrackingError

    if args.view is None:
        raise TrackingError("--landmarks, --compressed-point, --warp, --uncertainty and "
                            "--compare-* need --view cc|mlo|biopsy (the compression to track "
                            "into)")
    other = [o for o in ("label", "cc_point", "mlo_point", "cc_contour", "mlo_contour", "views")
             if getattr(args, o) is not None]
    if other:
        raise TrackingError(f"--view {args.view.lower()} tracks in 3-D: --"
                            f"{other[0].replace('_', '-')} belongs to the mammogram tracking; "
                            "run it without --view")
    if not any((args.mri_point, args.landmarks, args.compressed_point, args.warp,
                args.compare_mri, args.compare_landmarks)):
        raise TrackingError(f"--view {args.view.lower()}: nothing to track; give --mri-point, "
                            "--landmarks, --compressed-point, --warp or --compare-mri")
    if args.surrogate and not args.uncertainty:
        raise TrackingError("--surrogate gives the --uncertainty terms; add --uncertainty")
    if args.compare_landmarks and not args.landmarks:
        raise TrackingError("--compare-landmarks needs --landmarks (the same landmarks in "
                            "the MRI)")
    existing_file(args.landmarks, "--landmarks", "landmark file")
    existing_file(args.compare_landmarks, "--compare-landmarks", "landmark file")
    existing_file(args.compare_mri, "--compare-mri", "label map")
    writable_folder(args.out, "--out")
    writable_folder(args.cache, "--cache")
    from regtrack.privacy import identifiers_of_case_folder, pseudonymous_id, scrub_logs

    found = identifiers_of_case_folder(args.case)
    with scrub_logs(found):
        from regtrack.case import load_case
        from regtrack.tracking.compressed import (map_points, open_compressed, write_points,
                                                  write_warped)
        from regtrack.tracking.landmarks import read_landmarks

        landmarks = read_landmarks(args.landmarks) if args.landmarks else None  # before any work
        surrogate = None
        if args.surrogate:
            from regtrack.surrogate import Surrogate

            surrogate = Surrogate.load(args.surrogate)
        observed = read_landmarks(args.compare_landmarks) if args.compare_landmarks else None
        case = load_case(args.case, deep=False)
        case_id = pseudonymous_id(case.id, found)
        out = (Path(args.out) if args.out
               else Path("reports") / case_id / f"track_{args.view.lower()}")
        t0 = time.perf_counter()

        def progress(msg: str) -> None:
            console.print(f"[dim]{time.perf_counter() - t0:7.1f} s[/dim]  {msg}")

        if not logging.getLogger().isEnabledFor(logging.DEBUG):
            logging.getLogger("regtrack").setLevel(logging.WARNING)
        state = open_compressed(args.case, args.view, cache_dir=args.cache,
                                simulate=not args.no_simulate, progress=progress)
        mapped = []
        if args.mri_point is not None:
            mapped.append(map_points(state.dmap, ["mri-point"], [args.mri_point]))
        predicted = None
        if landmarks is not None:
            predicted = map_points(state.dmap, landmarks.names, landmarks.lps_mm)
            mapped.append(predicted)
        if args.compressed_point is not None:
            mapped.append(map_points(state.dmap, ["compressed-point"], [args.compressed_point],
                                     inverse=True))
        if args.uncertainty and mapped:
            import dataclasses

            from regtrack.tracking.sensitivity import point_sigma

            for i, m in enumerate(mapped):
                ps = point_sigma(args.case, state, m.names, m.given_lps_mm,
                                 inverse=m.direction != "mri->compressed", cache_dir=args.cache,
                                 simulate=not args.no_simulate, progress=progress,
                                 surrogate=surrogate)
                mapped[i] = dataclasses.replace(m, sigma_mm=ps.sigma_mm, sigma_terms_mm=ps.terms_mm,
                                                sigma_sources=ps.sources)
        sur_doc = None if surrogate is None else {
            "folder": str(args.surrogate), "used_for": "the uncertainty's c1, nu and plate terms",
            "validation_held_out": (surrogate.meta.get("validation") or {}).get("held_out", {}).get("pooled")}
        paths = write_points(out, state, mapped, surrogate=sur_doc) if mapped else []
        if state.view == "BIOPSY" and mapped and not args.no_pdf:
            from regtrack.pipeline.outputs import step_states
            from regtrack.report.biopsy import write_biopsy_report

            progress("report: biopsy.pdf (the needle target and the protocol)")
            paths.append(write_biopsy_report(out / "biopsy.pdf", state, mapped, case_id=case_id,
                                             states=step_states(state.sim)))
        if args.warp:
            paths += write_warped(out, state, progress=progress, pseudonym=case_id,
                                  keep_identifiers=args.keep_identifiers)
        if args.compare_mri or observed is not None:
            from regtrack.tracking.compressed import write_comparison

            path, doc = write_comparison(out, state, labels_path=args.compare_mri,
                                         predicted=predicted, observed=observed)
            paths.append(path)
            if "surface_distance" in doc:
                sd = doc["surface_distance"]
                console.print(f"skin vs the compressed MRI: RMS {sd['rms_mm']:.2f} mm, p95 "
                              f"{sd['p95_mm']:.2f} mm, max {sd['max_mm']:.2f} mm "
                              f"({sd['n_points']} skin nodes)", highlight=False)
            for r in doc.get("landmarks", []):
                console.print(f"{r['name']}: {r['distance_mm']:.1f} mm from the compressed "
                              "MRI's landmark", highlight=False)
        for m in mapped:
            for r in m.rows():
                a, b = r["mri_lps_mm"], r["compressed_lps_mm"]
                if m.direction != "mri->compressed":
                    a, b = b, a
                sigma = f" ± {r['sigma_mm']:.1f} mm (1 sigma)" if "sigma_mm" in r else ""
                console.print(f"{r['name']}: ({', '.join(f'{v:.1f}' for v in a)}) -> "
                              f"({', '.join(f'{v:.1f}' for v in b)}) LPS mm{sigma}, "
                              f"{m.direction}, moved {r['displacement_mm']:.1f} mm",
                              highlight=False)
        dt = time.perf_counter() - t0
        console.print(f"{state.view} (D = {state.summary.get('D') or 0:.2f}): "
                      f"{len(paths)} files written to {out} ({dt:.1f} s)")
    return 0


def _check_numbers(args: argparse.Namespace) -> None:
    """Finite coordinates for every point option (NaN/inf are refused before any work)."""
    import math

    from regtrack.errors import TrackingError

    for opt in ("mri_point", "cc_point", "mlo_point", "compressed_point"):
        value = getattr(args, opt)
        if value is not None and not all(math.isfinite(v) for v in value):
            raise TrackingError(f"--{opt.replace('_', '-')} {' '.join(map(str, value))}: "
                                "coordinates must be finite numbers")


def _check_on_image(case, points: dict, contours: dict) -> None:
    """Every (row, col) given on a real mammogram must lie on its pixel grid; checked from
    the DICOM header (Rows, Columns) before the registration that took 6-8 s."""
    import numpy as np
    import pydicom

    from regtrack.errors import TrackingError

    for v in {*points, *contours}:
        try:
            ds = pydicom.dcmread(case.views[v].mammogram, stop_before_pixels=True)
            rows, cols = int(ds.Rows), int(ds.Columns)
        except Exception:  # noqa: BLE001 - the reader names a bad DICOM later, in its own words
            continue
        pts = [np.asarray(points[v], float)[None]] if v in points else []
        if v in contours:
            pts.append(np.asarray(contours[v], float).reshape(-1, 2))
        for rc in pts:
            bad = (rc[:, 0] < 0) | (rc[:, 0] > rows - 1) | (rc[:, 1] < 0) | (rc[:, 1] > cols - 1)
            if bad.any():
                r, c = rc[np.argmax(bad)]
                kind = "point" if v in points and rc.shape[0] == 1 else "contour"
                raise TrackingError(f"--{v.lower()}-{kind}: (row {r:g}, col {c:g}) is outside "
                                    f"the {v} mammogram ({rows} rows x {cols} columns); give "
                                    "DICOM pixel coordinates (row, col) on that image")


def _check_label(case, label: str) -> None:
    """``--label``: its syntax, and a label value present in the MRI label map, checked
    before the mesh and simulations are prepared."""
    import numpy as np

    from regtrack.errors import TrackingError
    from regtrack.imaging.readers import read_label_map
    from regtrack.tracking.track import parse_label

    kind, value = parse_label(label)
    if kind != "label":
        return
    present = np.unique(read_label_map(case.mri.labels).data)
    if value not in present:
        raise TrackingError(f"--label {label}: label value {value} is not in the label map "
                            f"(values present: {', '.join(map(str, present.tolist()))}); "
                            "choose --label from those, or 'tumour'")
