"""``regtrack mesh``: label map -> tetrahedral breast model (.vtu + JSON + PNG)."""

from __future__ import annotations

import argparse

HELP = "build the finite-element breast model (tet mesh) from the MRI label map"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case", nargs="?", help="case folder (or its case.toml)")
    parser.add_argument("--out", help="output .vtu, or a folder (default: CASE/out/model.vtu)")
    parser.add_argument("--labels", help="label map file, instead of a case")
    parser.add_argument("--scheme", default="pelicano-simple", help="label preset with --labels")
    parser.add_argument("--side", choices=("L", "R"), help="breast to model")
    parser.add_argument("--target-nodes", type=int, help="approximate node count")
    parser.add_argument("--element-size", type=float, help="element size (mm)")
    parser.add_argument("--no-pictures", action="store_true", help="skip the PNG pictures")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import logging
    from pathlib import Path

    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from regtrack.errors import CaseError
    from regtrack.model.build import build_model
    from regtrack.model.config import MeshConfig
    from regtrack.model.io import save_model
    from regtrack.model.labels import get_scheme
    from regtrack.model.pictures import save_pictures

    from regtrack.cli._checks import existing_file, number_in_range

    log = logging.getLogger("regtrack.mesh")
    # the numbers first: a negative element size used to mean 8 minutes of mesher retries
    nodes_f = MeshConfig.__dataclass_fields__["target_nodes"].metadata
    size_f = MeshConfig.__dataclass_fields__["element_size_mm"].metadata
    number_in_range(args.target_nodes, "--target-nodes", ge=nodes_f["ge"], le=nodes_f["le"],
                    why="approximate node count of the mesh")
    number_in_range(args.element_size, "--element-size", unit="mm", gt=size_f["gt"],
                    le=size_f["le"], why="tetrahedron edge length")
    existing_file(args.labels, "--labels", "label map")
    if args.out is not None and Path(args.out).suffix == ".vtu":
        _checks_parent(args.out)
    elif args.out is not None:
        from regtrack.cli._checks import writable_folder

        writable_folder(args.out, "--out")
    nipple = None
    side = args.side
    if args.labels:
        from regtrack.imaging.readers import read_label_map

        labels = read_label_map(args.labels)
        scheme = get_scheme(args.scheme, where="--scheme")
        config = MeshConfig()
        out = Path(args.out or Path(args.labels).with_name("model.vtu"))
    elif args.case:
        from regtrack.case import load_case
        from regtrack.imaging.readers import read_label_map

        case = load_case(args.case, deep=False)
        labels = read_label_map(case.mri.labels)
        scheme = case.mri.scheme
        config = case.config("model")
        side = side or case.mri.side
        nipple = case.mri.nipple_lps_mm
        out = Path(args.out) if args.out else case.root / "out" / "model.vtu"
    else:
        raise CaseError("regtrack mesh: give a CASE folder or --labels FILE")
    if out.suffix != ".vtu":
        out = out / "model.vtu"
    over: dict = {}
    if args.target_nodes is not None:
        over["target_nodes"] = args.target_nodes
    if args.element_size is not None:
        over["element_size_mm"] = args.element_size
    config = dataclasses.replace(config, **over)
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), transient=True) as bar:
        task = bar.add_task("meshing", total=None)
        model = build_model(labels, scheme=scheme, config=config, side=side, nipple_lps=nipple,
                            progress=lambda msg: bar.update(task, description=msg))
    _drop_paths(model, args)
    save_model(model, out)
    if not args.no_pictures:
        save_pictures(model, out.with_suffix(""))
    q = model.meta["quality"]
    log.info("wrote %s: %d nodes, %d tets, min dihedral %.1f deg, gamma p5 %.2f, volume error %.2f%%",
             out, model.n_nodes, model.n_tets, q["min_dihedral_deg"], q["gamma_p5"], 100 * q["volume_error"])
    return 0


def _checks_parent(out: str) -> None:
    """``--out M.vtu``: its folder must be creatable and writable."""
    from pathlib import Path

    from regtrack.cli._checks import writable_folder
    from regtrack.errors import ConfigError

    if Path(out).is_dir():
        raise ConfigError(f"--out {out}: is a folder named like a .vtu file; give a file path "
                          "or another folder")
    writable_folder(Path(out).parent, "--out")


def _drop_paths(model, args: argparse.Namespace) -> None:
    """Keep folder names out of the model's JSON (they often carry the patient's name):
    the label map's path becomes its file name, the case folder ``<case>``, and the DICOM
    identifiers of a case's headers are redacted (announced)."""
    from pathlib import Path

    from regtrack.privacy import Identifiers, identifiers_of_case_folder

    ids = identifiers_of_case_folder(args.case) if args.case else Identifiers()
    src = model.meta.get("source")
    if isinstance(src, str) and src:
        model.meta["source"] = Path(src).name
    model.meta.update(ids.redact_obj(dict(model.meta), "the model's metadata"))
