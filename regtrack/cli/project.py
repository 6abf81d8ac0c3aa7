"""``regtrack project``: virtual mammogram of a simulation result (JSON in mm + PNGs)."""

from __future__ import annotations

import argparse

HELP = "virtual mammogram of a simulation result: contours (JSON, mm), X-ray-like image, overlay PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="model .vtu (with its JSON sidecar)")
    parser.add_argument("--result", required=True,
                        help="result .vtu with point data 'displacement' (mm)")
    parser.add_argument("--view", required=True, type=str.upper, choices=("CC", "MLO"))
    parser.add_argument("--step", default=None,
                        help="step to project (point data 'displacement_<STEP>'); default the final "
                        "'displacement'")
    parser.add_argument("--angle", type=float, default=None,
                        help="plate angle in degrees (default: from the result's JSON, else 0 CC / 45 MLO)")
    parser.add_argument("--pixel", type=float, default=None, help="pixel size in mm (default 0.25)")
    parser.add_argument("--sid", type=float, default=None,
                        help="source-to-image distance in mm for a magnified projection "
                        "(default: orthogonal projection, as in the paper)")
    parser.add_argument("--out", required=True, help="output folder")


def _config(args):
    from regtrack.config import parse_section
    from regtrack.errors import ConfigError
    from regtrack.virtual.config import VirtualConfig

    table = {}
    if args.pixel is not None:
        table["pixel_mm"] = args.pixel
    if args.sid is not None:
        table["source_to_image_mm"] = args.sid
    cfg, problems, _ = parse_section(VirtualConfig, table, where="regtrack project options")
    if problems:
        raise ConfigError("; ".join(problems).replace("pixel_mm", "--pixel").replace(
            "source_to_image_mm", "--sid"))
    return cfg


def run(args: argparse.Namespace) -> int:
    import logging
    from pathlib import Path

    from regtrack import _io
    from regtrack.config import to_table
    from regtrack.model.io import load_model
    from regtrack.virtual import figures, project_model
    from regtrack.virtual.io import read_result_positions, result_plate_angle
    from regtrack.virtual.project import default_frame

    from regtrack.cli._checks import writable_folder

    log = logging.getLogger("regtrack.project")
    writable_folder(args.out, "--out")
    cfg = _config(args)
    model = load_model(args.model)
    pos = read_result_positions(args.result, model, step=args.step)
    angle = args.angle if args.angle is not None else result_plate_angle(args.result, args.view)
    frame = default_frame(pos, args.view, model.frame.side, angle_deg=angle)
    vm = project_model(model, pos, view=args.view, config=cfg, frame=frame,
                       source_name=f"virtual:{Path(args.result).name}")
    out = Path(args.out)
    stem = f"virtual_{args.view.lower()}" + (f"_{args.step}" if args.step else "")
    doc = vm.view.to_dict()
    doc.update(closed_contour_mm=vm.closed_contour, config=to_table(cfg),
               # file names only: the folders often carry the patient's name
               model=Path(args.model).name, result=Path(args.result).name, step=args.step,
               grid={"origin_mm": list(vm.grid.origin), "pixel_mm": vm.grid.spacing,
                     "shape": list(vm.grid.shape)})
    _io.write_json(out / f"{stem}.json", doc)
    figures.save_xray_png(vm, out / f"{stem}_xray.png")
    figures.save_overlay_png(vm, out / f"{stem}_overlay.png",
                             title=f"virtual {args.view} of {Path(args.result).name}")
    log.info("wrote %s.json, %s_xray.png and %s_overlay.png to %s (%d tumour contour(s))",
             stem, stem, stem, out, len(vm.view.tumour_contours))
    return 0
