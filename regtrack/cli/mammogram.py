"""``regtrack mammogram``: what is extracted from a real mammogram (JSON in mm + overlay PNG).

Two forms::

    regtrack mammogram CASE --view cc [--out DIR]
    regtrack mammogram --dicom FILE [--spacing R C] [--view cc] [--laterality L] --out DIR
"""

from __future__ import annotations

import argparse

HELP = "extract breast contour, nipple and tumour from a real mammogram (JSON in mm, overlay PNG)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case", nargs="?", default=None,
                        help="case folder or case.toml (its [views.<VIEW>] entry is used)")
    parser.add_argument("--view", type=str.upper, choices=("CC", "MLO"), default=None,
                        help="view to extract (required with CASE; with --dicom it overrides "
                        "the DICOM tags)")
    parser.add_argument("--dicom", default=None, help="a DICOM mammogram file (instead of CASE)")
    parser.add_argument("--spacing", type=float, nargs=2, metavar=("R", "C"), default=None,
                        help="pixel spacing (row, col) in mm for DICOMs without a spacing tag")
    parser.add_argument("--laterality", type=str.upper, choices=("L", "R"), default=None,
                        help="with --dicom: override the DICOM laterality")
    parser.add_argument("--nipple", type=float, nargs=2, metavar=("ROW", "COL"), default=None,
                        help="with --dicom: nipple pixel (row, col) in the DICOM grid")
    parser.add_argument("--tumour-seed", type=float, nargs=2, metavar=("ROW", "COL"), default=None,
                        help="a pixel (row, col, DICOM grid) inside the tumour: outline it "
                        "semi-automatically")
    parser.add_argument("--out", default=None,
                        help="output folder (default: <case>/output with CASE; required with "
                        "--dicom)")


def _inputs_from_case(args) -> dict:
    from regtrack.case import load_case, read_tumour_mask, read_tumour_polygons
    from regtrack.errors import CaseError

    if args.view is None:
        raise CaseError(f"{args.case}: give --view CC or --view MLO")
    case = load_case(args.case, deep=False)
    if args.view not in case.views:
        have = ", ".join(case.views) or "none"
        raise CaseError(f"{case.toml_path}: no [views.{args.view}] section (views: {have}); add "
                        f"one with mammogram = \"<file>.dcm\"")
    v = case.views[args.view]
    out = {
        "dicom": v.mammogram,
        "spacing": args.spacing or v.pixel_spacing_mm,
        "nipple_px": v.nipple_px,
        "tumour_polygon_px": read_tumour_polygons(v.tumour_polygon) if v.tumour_polygon else None,
        "tumour_mask": read_tumour_mask(v.tumour_mask) if v.tumour_mask else None,
        "laterality": None,
        "view": args.view,
        "out": args.out or (case.root / "output"),
        "case_id": case.id,
        "side": getattr(case.mri, "side", None),
    }
    return out


def run(args: argparse.Namespace) -> int:
    import logging
    from pathlib import Path

    from regtrack import _io
    from regtrack.errors import InputFileError, RegtrackError
    from regtrack.imaging.mammogram import extract_view, read_mammogram, write_overlay

    log = logging.getLogger("regtrack.mammogram")
    if (args.case is None) == (args.dicom is None):
        raise RegtrackError("regtrack mammogram: give either CASE or --dicom FILE (not both)")
    if args.case is not None:
        inp = _inputs_from_case(args)
    else:
        if args.out is None:
            raise RegtrackError("regtrack mammogram: --out DIR is required with --dicom")
        inp = {"dicom": Path(args.dicom), "spacing": args.spacing, "nipple_px": args.nipple,
               "tumour_polygon_px": None, "tumour_mask": None, "laterality": args.laterality,
               "view": args.view, "out": args.out, "case_id": None, "side": None}
    if not Path(inp["dicom"]).is_file():
        raise InputFileError(f"{inp['dicom']}: mammogram not found")
    img = read_mammogram(inp["dicom"], pixel_spacing_mm=inp["spacing"], view=inp["view"],
                         laterality=inp["laterality"])
    if inp["side"] and inp["side"] != img.laterality:
        log.warning("%s: laterality %s differs from the case's breast side %s", inp["dicom"],
                    img.laterality, inp["side"])
    view = extract_view(img, tumour_polygon_px=inp["tumour_polygon_px"],
                        tumour_mask=inp["tumour_mask"], tumour_seed_px=args.tumour_seed,
                        nipple_px=inp["nipple_px"])
    out = Path(inp["out"])
    stem = f"mammogram_{view.view.lower()}"
    doc = view.to_dict()
    doc["case_id"] = inp["case_id"]
    doc["dicom"] = str(inp["dicom"])
    _io.write_json(out / f"{stem}.json", doc)
    write_overlay(view, out / f"{stem}_overlay.png")
    nip = view.meta.get("nipple", {})
    log.info("%s%s: contour %d points, breast area %.0f mm^2, nipple (%.1f, %.1f) mm (%s, "
             "confidence %.2f), %d tumour contour(s); wrote %s.json and %s_overlay.png to %s",
             view.laterality, view.view, len(view.breast_contour), view.meta["breast_area_mm2"],
             view.nipple[0], view.nipple[1], nip.get("method", "?"), nip.get("confidence", 0.0),
             len(view.tumour_contours), stem, stem, out)
    return 0
