"""``regtrack mammogram``: what is extracted from a real mammogram (JSON in mm + overlay PNG).

Two forms::

    regtrack mammogram CASE --view cc [--out DIR]
    regtrack mammogram --dicom FILE [--spacing R C] [--view cc] [--laterality L] --out DIR

No identifier reaches the outputs: the input's path (folder and file names often carry the
patient's name) is written as ``<mammogram>`` with the file's SHA-256, and the DICOM
header's identifying values (:data:`regtrack.privacy.IDENTIFYING_KEYWORDS`) are redacted
from the JSON, the overlay title and the log, with a warning saying what was removed.
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
    parser.add_argument("--keep-identifiers", action="store_true",
                        help="write the input path and the DICOM identifiers as they are")


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
    import dataclasses
    import logging
    from pathlib import Path

    from regtrack import _io
    from regtrack.cli._checks import existing_file, number_in_range, writable_folder
    from regtrack.errors import InputFileError, RegtrackError
    from regtrack.imaging.mammogram import extract_view, read_mammogram, write_overlay
    from regtrack.privacy import Identifiers, scrub_logs

    log = logging.getLogger("regtrack.mammogram")
    if (args.case is None) == (args.dicom is None):
        raise RegtrackError("regtrack mammogram: give either CASE or --dicom FILE (not both)")
    for value in args.spacing or ():
        number_in_range(value, "--spacing", unit="mm", gt=0, le=10,
                        why="pixel spacing (row, col)")
    for opt in ("nipple", "tumour_seed"):
        for value in getattr(args, opt) or ():
            number_in_range(value, f"--{opt.replace('_', '-')}", ge=0,
                            why="a (row, col) pixel of the DICOM grid")
    writable_folder(args.out, "--out")
    existing_file(args.dicom, "--dicom", "DICOM mammogram")
    if args.case is not None:
        from regtrack.privacy import identifiers_of_case_folder, pseudonymous_id

        case_ids = Identifiers() if args.keep_identifiers else identifiers_of_case_folder(args.case)
        with scrub_logs(case_ids):
            inp = _inputs_from_case(args)
        if not args.keep_identifiers:
            inp["case_id"] = pseudonymous_id(inp["case_id"], case_ids)
    else:
        case_ids = Identifiers()
        if args.out is None:
            raise RegtrackError("regtrack mammogram: --out DIR is required with --dicom")
        inp = {"dicom": Path(args.dicom), "spacing": args.spacing, "nipple_px": args.nipple,
               "tumour_polygon_px": None, "tumour_mask": None, "laterality": args.laterality,
               "view": args.view, "out": args.out, "case_id": None, "side": None}
    if not Path(inp["dicom"]).is_file():
        raise InputFileError(f"{inp['dicom']}: mammogram not found")
    out = Path(inp["out"])
    writable_folder(out, "--out")
    ids = Identifiers() if args.keep_identifiers else _identifiers(Path(inp["dicom"]), case_ids)
    with scrub_logs(ids):
        img = read_mammogram(inp["dicom"], pixel_spacing_mm=inp["spacing"], view=inp["view"],
                             laterality=inp["laterality"])
        if inp["side"] and inp["side"] != img.laterality:
            log.warning("%s: laterality %s differs from the case's breast side %s",
                        inp["dicom"], img.laterality, inp["side"])
        view = extract_view(img, tumour_polygon_px=inp["tumour_polygon_px"],
                            tumour_mask=inp["tumour_mask"], tumour_seed_px=args.tumour_seed,
                            nipple_px=inp["nipple_px"])
    if not args.keep_identifiers:
        view = dataclasses.replace(view, source=ids.scrub(str(view.source)),
                                   meta=ids.redact_obj(view.meta, "the mammogram's notes"))
    stem = f"mammogram_{view.view.lower()}"
    doc = view.to_dict()
    doc["case_id"] = inp["case_id"]
    doc["dicom"] = str(inp["dicom"]) if args.keep_identifiers else "<mammogram>"
    doc["dicom_sha256"] = _sha256(Path(inp["dicom"]))
    _io.write_json(out / f"{stem}.json", doc)
    write_overlay(view, out / f"{stem}_overlay.png", title=f"{view.laterality}{view.view}"
                  + (f"  {Path(inp['dicom']).name}" if args.keep_identifiers else ""))
    nip = view.meta.get("nipple", {})
    log.info("%s%s: contour %d points, breast area %.0f mm^2, nipple (%.1f, %.1f) mm (%s, "
             "confidence %.2f), %d tumour contour(s); wrote %s.json and %s_overlay.png to %s",
             view.laterality, view.view, len(view.breast_contour), view.meta["breast_area_mm2"],
             view.nipple[0], view.nipple[1], nip.get("method", "?"), nip.get("confidence", 0.0),
             len(view.tumour_contours), stem, stem, out)
    return 0


def _identifiers(dicom: Path, ids):
    """What must not reach an output: the DICOM header's identifying values, the case
    folder (``<case>``) and the input's path in every spelling (as given, absolute,
    resolved), shown as ``<mammogram>``; added to ``ids``."""
    import os

    from regtrack.privacy import read_identifiers

    read_identifiers(dicom, ids)
    for form in {str(dicom), os.path.abspath(dicom), str(dicom.resolve())}:
        ids.paths[form] = "<mammogram>"
    return ids


def _sha256(path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()
