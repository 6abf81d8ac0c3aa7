"""Build the bundled sample cases: ``sample_cases/phantom01``, ``phantom02`` and ``pelicano_exam03``.

Usage::

    .venv/bin/python pipelines/make_sample_cases.py [--only phantom01|phantom02|pelicano_exam03]
        [--out sample_cases] [--shared-data ../shared/data]

* ``phantom01``: the default :class:`regtrack.phantom.PhantomParams` (seed 1): a DICOM MR
  series (one file per slice, JPEG 2000 lossless), the label map (int8 NIfTI), simulated
  CC and MLO DICOM MG mammograms with tumour polygons and nipple pixels
  (:mod:`regtrack.phantom.case_mammo`, minutes: a mesh and two protocol simulations), and
  the ground truth in ``truth/`` (never read by the pipeline).
* ``phantom02``: :data:`PHANTOM02` (seed 2, a *left* breast, a smaller medial-inferior
  tumour; mammogram noise seed 2, truth mesh 7.0 mm), made the same way but without the
  DICOM MR series (label map, mammograms, annotations and truth only) to keep the
  repository small.
* ``pelicano_exam03``: the right breast of Pelicano exam 03 (simple labels), cropped with
  its real-world geometry intact, int8 NIfTI, with the citation.  Needs ../shared/data.

All are deterministic: re-running gives identical label maps and DICOM files.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from regtrack import _io
from regtrack.imaging.readers import read_label_map, write_dicom_series, write_label_map
from regtrack.imaging.volume import LabelVolume
from regtrack.phantom import PhantomParams, make_phantom
from regtrack.phantom.dicom_mg import IHE_ORIENTATION

log = logging.getLogger("make_sample_cases")
REPO = Path(__file__).resolve().parents[1]

PELICANO_CITATION = """\
* A. C. Pelicano et al., "Development of 3D MRI-Based Anatomically Realistic Models of Breast
  Tissues and Tumours for Microwave Imaging Diagnosis", *Sensors*, 2021.
* A. C. Pelicano et al., *PLoS One*, 2024 (the companion paper of the breast models
  repository; see that repository for the full reference).
"""


# ----------------------------------------------------------------------------- phantoms

#: phantom02: a left breast with another texture (seed 2) and a smaller tumour, medial and
#: inferior of the nipple axis and deeper than phantom01's (35 mm from the chest wall)
PHANTOM02 = PhantomParams(seed=2, side="L", tumour_size_mm=(18.0, 16.0, 18.0),
                          tumour_offset_mm=(-12.0, 35.0, -15.0))


def _side_word(side: str) -> str:
    return "right" if side == "R" else "left"


def phantom_case_toml(case_id: str, truth: dict, views: dict | None = None, *, series: bool = True,
                      tissue_c1_kpa: tuple[float, float] | None = None) -> str:
    """case.toml of a phantom; ``tissue_c1_kpa`` = the truth's (fat, gland) c1, written as
    the case's ``[mechanics]`` fat/gland composition (with the mammograms only)."""
    nip = ", ".join(f"{v:.2f}" for v in truth["nipple_lps_mm"])
    prm = truth["params"]
    size = "x".join(f"{v:g}" for v in prm["tumour_size_mm"])
    series_line = 'series = "mri/dicom"\n' if series else ""
    head = f'''# Synthetic prone breast phantom made by pipelines/make_sample_cases.py
# (regtrack.phantom, seed {prm["seed"]}).  Ground truth: truth/ (never read by the pipeline).
[case]
id = "{case_id}"
title = "Synthetic prone breast phantom ({_side_word(prm["side"])} breast, {size} mm tumour)"

[mri]
labels = "mri/labels.nii.gz"
{series_line}scheme = "pelicano-detailed"
side = "{prm["side"]}"
# the generator's exact nipple (LPS, mm) is in truth/; uncomment to override detection:
# nipple_lps_mm = [{nip}]

[model]
# a coarse patient model keeps `make demo` and CI to minutes (both compressions converge
# at this size); --set model.target_nodes=10000 for the paper's resolution
target_nodes = 1500
'''
    if not views:
        return head + '''
# Mammograms: run pipelines/make_sample_cases.py without --no-mammograms.
'''
    out = [head]
    if tissue_c1_kpa is not None:
        fat, gland = tissue_c1_kpa
        out.append(f'''
[mechanics]
# The phantom's tissue is heterogeneous, fat and gland with the c1 below (truth/).  The model
# stays the paper's homogenised one: one c1 for all tissue, the volume-weighted mean of these
# over the case's MRI labels (tissue_model = "composition").  Delete this section for the
# paper's c1 = 0.54 kPa; a study or calibration that sets c1 uses that c1 instead.
tissue_model = "composition"
fat_c1_kpa = {fat:g}
gland_c1_kpa = {gland:g}
''')
    for v, e in views.items():
        out.append(f'''
[views.{v}]  # simulated DICOM MG; tumour outline and nipple are the true projections
mammogram = "{e["mammogram"]}"
tumour_polygon = "{e["tumour_polygon"]}"
nipple_px = [{e["nipple_px"][0]:.2f}, {e["nipple_px"][1]:.2f}]  # [row, col], DICOM grid
''')
    return "".join(out)


def make_phantom_case(out: Path, case_id: str, params: PhantomParams, *, series: bool = True,
                      mammograms: bool = True, truth_params=None, readme_note: str = "") -> Path:
    """Write a phantom case folder; returns it.

    The MRI part (labels, DICOM series when ``series``, phantom truth) does not depend on
    the mammograms, so it is byte-identical with or without them.
    """
    case = out / case_id
    mri, labels, truth = make_phantom(params)
    write_label_map(labels, case / "mri" / "labels.nii.gz")
    if series:
        write_dicom_series(mri, case / "mri" / "dicom", patient=case_id,
                           series_description="synthetic T1 prone breast (regtrack.phantom)",
                           uid_seed=f"regtrack-{case_id}", progress=True)
    _io.write_json(case / "truth" / "phantom_truth.json", truth)
    views, mammo_truth, tissue = None, None, None
    if mammograms:
        from regtrack.phantom.case_mammo import make_case_mammograms
        from regtrack.phantom.mammo_params import MammoTruthParams

        # simulate from the label map as bundled (float32 geometry of the NIfTI), so that a
        # re-simulation from the case's files follows the same path
        bundled = read_label_map(case / "mri" / "labels.nii.gz")
        with _solver_progress() as progress:
            made = make_case_mammograms(case, bundled, truth, params=truth_params or MammoTruthParams(),
                                        case_id=case_id, progress=progress)
        views, mammo_truth = made["views"], made["truth"]
        tp = truth_params or MammoTruthParams()
        tissue = (tp.fat_c1_kpa, tp.gland_c1_kpa)
    _io.write_text(case / "case.toml", phantom_case_toml(case_id, truth, views, series=series,
                                                         tissue_c1_kpa=tissue))
    readme = phantom_readme(case_id, truth, series=series)
    if mammo_truth is not None:
        readme += mammo_readme(mammo_truth) + readme_note
    _io.write_text(case / "README.md", readme)
    return case


def make_phantom01(out: Path, *, case_id: str = "phantom01", mammograms: bool = True,
                   truth_params=None) -> Path:
    """``phantom01``: the default :class:`PhantomParams`, with its DICOM MR series."""
    return make_phantom_case(out, case_id, PhantomParams(), series=True, mammograms=mammograms,
                             truth_params=truth_params)


def make_phantom02(out: Path, *, case_id: str = "phantom02", mammograms: bool = True,
                   truth_params=None) -> Path:
    """``phantom02``: :data:`PHANTOM02` (left breast, seed 2), without a DICOM MR series.

    Truth simulation: :func:`phantom02_truth_params` unless ``truth_params`` is given.
    """
    return make_phantom_case(out, case_id, PHANTOM02, series=False, mammograms=mammograms,
                             truth_params=truth_params or phantom02_truth_params(), readme_note=PHANTOM02_NOTE)


def phantom02_truth_params(**changes):
    """phantom02's truth settings: the defaults with the detector-noise seed 2 and a 7.0 mm mesh.

    At the default 7.5 mm (1,671 nodes) the MLO compression of this phantom did not
    converge (first increment 0.1, and 0.05; the CC did); at 7.0 mm (1,968 nodes) both
    views converge.
    """
    from regtrack.phantom.mammo_params import MammoTruthParams

    return dataclasses.replace(MammoTruthParams(), **{"seed": PHANTOM02.seed, "element_size_mm": 7.0, **changes})


PHANTOM02_NOTE = """
The truth mesh is finer than phantom01's (element size 7.0 mm instead of 7.5 mm): at 7.5 mm
(1,671 nodes) the MLO truth compression of this phantom did not converge, with a first
increment of 0.1 and of 0.05.
"""


class _solver_progress:
    """A rich progress bar fed by the solver's ``progress(step_name, t)`` callback."""

    def __enter__(self):
        from rich.progress import Progress

        self._bar = Progress(transient=True)
        self._bar.start()
        self._task = self._bar.add_task("truth simulation", total=1.0)
        return self

    def __call__(self, step_name: str, t: float, **info) -> None:  # info: plate force, D
        self._bar.update(self._task, completed=float(t), description=f"truth: {step_name}")

    def __exit__(self, *exc):
        self._bar.stop()
        return False


def mammo_readme(t: dict) -> str:
    """README section describing the mammograms and the mismatch built into the case."""
    mm = t["mismatch_vs_pipeline_defaults"]
    rows = []
    for v, d in t["views"].items():
        sim = d["simulation"]
        rows.append(f"| {v} | {d['rotation_deg']:+.1f} | ({d['shift_mm'][0]:+.1f}, {d['shift_mm'][1]:+.1f}) "
                    f"| {sim['D']:.3f} | {sim['upper_force_N']:.1f} | {d['image_shape'][0]}x{d['image_shape'][1]} "
                    f"| {d['dicom_bytes'] / 1e3:.0f} kB ({d['compression_ratio_measured']:.1f}:1) |")
    p = t["params"]
    side = next(iter(t["views"].values()))["laterality"]
    word = _side_word(side)
    cc, mlo = ("\\".join(IHE_ORIENTATION[(side, v)]) for v in ("CC", "MLO"))
    return f"""
## Mammograms (`mammo/`) and their hidden truth (`truth/mammo_truth.json`)

`mammo/cc.dcm` and `mammo/mlo.dcm` are simulated DICOM MG "for presentation" images of
the {word} breast (ImageLaterality {side}, ViewPosition CC / MLO, PatientOrientation `{cc}` /
`{mlo}` as the IHE hanging stores a {word} breast, ImagerPixelSpacing = PixelSpacing =
{p['pixel_mm']} mm, {p['bits_stored']}-bit MONOCHROME2, JPEG 2000).  `mammo/*_tumour.json` hold
the true projected tumour outline and case.toml the true projected nipple (`nipple_px`),
both in the DICOM's own pixel grid.

How they were made (`regtrack.phantom.case_mammo`, seed {p['seed']}): the phantom was meshed
({t['model']['n_nodes']} nodes) and compressed with the project's own protocol engine (gravity
unloading, lower plate, standing gravity, upper plate to the target D), projected
orthogonally on the plate, moved in the image plane by a known rotation about the nipple
and a shift, and rendered by Beer-Lambert line integrals through fat, gland and tumour
(Johns & Yaffe attenuation at 20 keV) with a skin line and Poisson quantum noise.

| view | rotation (deg) | shift (mm) | true D | plate force (N) | pixels | DICOM |
|---|---|---|---|---|---|---|
{chr(10).join(rows)}

**Model mismatch built into the case** (the pipeline runs with its defaults):

* tissue: {mm['tissue']};
* Poisson ratio: {mm['nu']};
* friction: {mm['friction']};
* mesh: {mm['mesh']};
* solver: {mm['solver']};
* patient positioning: in-plane rotation CC {p['rotation_cc_deg']:+g} deg, MLO {p['rotation_mlo_deg']:+g} deg about
  the nipple (sense of `regtrack.registration`: R = [[c, -s], [s, c]] with y down), shifts as in the table;
* detector: {mm['detector']};
* the same as the pipeline: {mm['same_as_pipeline']}.

`truth/mammo_truth.json` gives, per view, the rotation and shift, the nipple and the tumour
centroid in the DICOM grid (`dicom_rc`) and in the canonical mm frame of the image as read
(`canonical_mm`, chest wall on the left), the projected 3-D tumour centroid, the full
plate-to-image map, D, T0, the plate forces and the solver figures.  Tests use it; the
pipeline must not.
"""


def _fmt_truth(t: dict) -> dict:
    f = lambda v: "[" + ", ".join(f"{x:.1f}" for x in v) + "]"  # noqa: E731
    return {"nipple": f(t["nipple_lps_mm"]), "tumour": f(t["tumour_centroid_lps_mm"]),
            "extent": f(t["tumour_extent_lps_mm"]), "tvol": f"{t['tumour_volume_mm3']:.0f}",
            "bvol": f"{t['breast_mound_volume_mm3'] / 1000:.0f}", "shape": "x".join(map(str, t["shape"]))}


PHANTOM_README = """\
# {case_id}: synthetic prone breast phantom

Made by `pipelines/make_sample_cases.py` with `regtrack.phantom.make_phantom({call})`
({what}).  Nothing here comes from a patient.

{mri}* `mri/labels.nii.gz`: label map on {grid}, detailed Pelicano convention: -3 tumour,
  -2 skin (with the nipple), -1 pectoral muscle, 0 background, 1-3 fibroglandular,
  4 transition, 5-7 fat.
* `truth/phantom_truth.json`: ground truth (the pipeline never reads it): nipple {nipple} mm,
  tumour centroid {tumour} mm and extent {extent} mm (LPS), tumour volume {tvol} mm^3,
  breast mound volume {bvol} cm^3, and every generator parameter.
* `case.toml`: the case description.
"""

PHANTOM_README_SERIES = """\
* `mri/dicom/`: T1-like MR series, one file per axial slice (MR Image Storage, JPEG 2000
  lossless), {shape} voxels of 0.66 x 0.66 x 1.4 mm, head-first prone, LPS geometry in
  ImagePositionPatient / ImageOrientationPatient / PixelSpacing / SliceThickness.
"""


def phantom_readme(case_id: str, truth: dict, *, series: bool = True) -> str:
    """The case README's phantom part (the mammogram part is :func:`mammo_readme`)."""
    f = _fmt_truth(truth)
    norm = lambda v: tuple(v) if isinstance(v, (list, tuple)) else v  # noqa: E731  (JSON gives lists)
    prm = {k: norm(v) for k, v in truth["params"].items()}
    default = {k: norm(v) for k, v in dataclasses.asdict(PhantomParams()).items()}
    if prm == default:
        call, what = "PhantomParams()", "seed 1"
    else:
        changed = ", ".join(f"{k}={v!r}" for k, v in prm.items() if v != default[k])
        call, what = f"PhantomParams({changed})", f"seed {prm['seed']}, {_side_word(prm['side'])} breast"
    if series:
        mri, grid = PHANTOM_README_SERIES.format(shape=f["shape"]), "the same grid"
    else:
        mri = ("* No MR series (`[mri] series`), to keep the repository small: the pipeline needs only\n"
               "  the label map, and the same call regenerates the T1-like MRI on its grid.\n")
        grid = (f"a grid of {f['shape']} voxels of 0.66 x 0.66 x 1.4 mm\n  (axial, LPS geometry in "
                "the NIfTI header)")
    return PHANTOM_README.format(case_id=case_id, call=call, what=what, mri=mri, grid=grid, **f)


# ----------------------------------------------------------------------------- pelicano


def _lr_axis(vol: LabelVolume) -> int:
    """Array axis closest to the LPS x (left-right) direction."""
    return int(np.argmax(np.abs(vol.direction[0, :])))


def _bin_min(keys: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    out = np.full(n, np.inf)
    np.minimum.at(out, keys, values)
    return out


def crop_tumour_breast(vol: LabelVolume, *, tumour_labels=(-3, -4), muscle_label: int = -1,
                       min_thickness_mm: float = 25.0, rel_thickness: float = 0.4, margin_mm: float = 15.0,
                       bin_mm: float = 2.0) -> tuple[LabelVolume, dict]:
    """Crop the breast holding the tumour, keeping its muscle and skin and the LPS affine.

    Works in LPS coordinates (any voxel orientation).  On a grid of ``bin_mm`` columns in
    the (x = LR, z = SI) plane:

    * the cleavage is the LR position between the two breasts where the body's anterior
      extent (min y) is most posterior;
    * a column belongs to the breast when it holds muscle and the body reaches more than
      ``max(min_thickness_mm, rel_thickness * thickest)`` anterior of the column's muscle
      front (the chest wall), on the tumour's side, connected to the thickest column (this
      leaves out the chest and abdomen wall, which are thinner than the breast);
    * the box spans those columns plus ``margin_mm`` (never past the cleavage), from
      ``margin_mm`` anterior of the breast to 3 mm behind the muscle under it.
    """
    data = vol.data
    idx = np.argwhere(data != 0)
    xyz = vol.index_to_world(idx)
    lab = data[tuple(idx.T)]
    tum = np.isin(lab, tumour_labels)
    if not tum.any():
        raise ValueError(f"{vol.source}: no tumour label {tumour_labels}")
    x_t = xyz[tum, 0].mean()
    # cleavage from the anterior extent per LR bin
    bx = np.floor(xyz[:, 0] / bin_mm).astype(int)
    bx0 = bx.min()
    front_x = _bin_min(bx - bx0, xyz[:, 1], bx.max() - bx0 + 1)
    cx = (np.arange(front_x.size) + bx0 + 0.5) * bin_mm
    ok = np.isfinite(front_x)
    mid = 0.5 * (cx[ok].min() + cx[ok].max())
    peaks = [cx[ok & sel][np.argmin(front_x[ok & sel])] for sel in (cx < mid, cx >= mid)]
    between = ok & (cx > min(peaks)) & (cx < max(peaks))
    cleavage = float(cx[between][np.argmax(front_x[between])])
    side = "R" if x_t < cleavage else "L"  # LPS: patient right is -x
    # breast columns: body far anterior of the chest wall
    bz = np.floor(xyz[:, 2] / bin_mm).astype(int)
    bz0 = bz.min()
    nz = bz.max() - bz0 + 1
    key = (bx - bx0) * nz + (bz - bz0)
    n = front_x.size * nz
    front = _bin_min(key, xyz[:, 1], n)
    mus = lab == muscle_label
    muscle_front = _bin_min(key[mus], xyz[mus, 1], n)
    half = xyz[:, 0] < cleavage if side == "R" else xyz[:, 0] >= cleavage
    thick = np.zeros(n)
    has = np.isfinite(muscle_front) & np.isfinite(front)
    thick[has] = muscle_front[has] - front[has]
    side_cols = np.zeros(n, bool)
    side_cols[key[half]] = True
    thick[~side_cols] = 0.0
    thr = max(min_thickness_mm, rel_thickness * thick.max())
    comp, _ = ndimage.label((thick > thr).reshape(-1, nz))
    col_breast = (comp.ravel() == comp.ravel()[np.argmax(thick)]) & (thick > thr)
    breast = half & col_breast[key]
    if not breast.any():
        raise ValueError(f"{vol.source}: no breast column thicker than {min_thickness_mm} mm")
    lo_w = xyz[breast].min(0) - margin_mm
    hi_w = xyz[breast].max(0) + margin_mm
    in_lr_si = ((xyz[:, 0] >= lo_w[0]) & (xyz[:, 0] <= hi_w[0]) & (xyz[:, 2] >= lo_w[2])
                & (xyz[:, 2] <= hi_w[2]) & half)
    hi_w[1] = xyz[in_lr_si & mus, 1].max() + 3.0
    if side == "R":
        hi_w[0] = min(hi_w[0], cleavage)
    else:
        lo_w[0] = max(lo_w[0], cleavage)
    corners = np.array([[a, b, c] for a in (lo_w[0], hi_w[0]) for b in (lo_w[1], hi_w[1])
                        for c in (lo_w[2], hi_w[2])])
    ijk = vol.world_to_index(corners)
    lo = np.maximum(np.floor(ijk.min(0)).astype(int), 0)
    hi = np.minimum(np.ceil(ijk.max(0)).astype(int) + 1, vol.shape)
    cropped = vol.crop(lo, hi)
    info = {"side": side, "cleavage_lps_x_mm": cleavage, "index_lo": lo.tolist(),
            "index_hi": hi.tolist(), "source_shape": list(vol.shape),
            "source_affine": vol.affine.tolist()}
    return cropped, info


PELICANO_README = """\
# pelicano_exam{exam}: one real breast (Pelicano exam {exam}, {side_word} breast)

`mri/labels.nii.gz` is the {side_word} breast of exam {exam} of the Pelicano breast models,
cropped from `Exam_{exam}/{src_name}` (simple labels: -4 benign tumour, -3 malignant tumour,
-2 skin, -1 muscle, 0 background, 1 fat and gland) and stored as int8 gzip NIfTI.  Only the
crop and the file format changed: the labels and the real-world geometry (origin, spacing,
direction in LPS, from the MetaImage header) are the original ones; `provenance.json` gives
the crop box in the original voxel indices and the original affine.

Published tumour of this exam: right breast, small malignant (8.5 x 11.2 x 9.2 mm).
Derived from 3.0 T prone breast MRI at Hospital da Luz, Lisbon.  There are no mammograms
for this exam, so the case has no `[views.*]`.

## Source and citation

The label maps were made and published for research by A. C. Pelicano and colleagues.
If you use this case, cite:

{citation}
## Terms

As stated in the project's data notes: the Pelicano label maps were "made by other people and
published for research"; this repository may bundle exactly this one cropped, single-breast,
compressed label map as a real-geometry sample case, with this citation.  Use it for research
and testing only, and cite the papers above.  No other file of that data set is part of this
repository.
"""


def pelicano_case_toml(exam: str, side: str) -> str:
    return f'''# One real breast from the Pelicano breast models (exam {exam}); see README.md for the citation.
[case]
id = "pelicano_exam{exam}"
title = "Pelicano exam {exam}, {"right" if side == "R" else "left"} breast (real MRI-derived label map)"

[mri]
labels = "mri/labels.nii.gz"
scheme = "pelicano-simple"
side = "{side}"

# No mammograms are published for this exam; add [views.CC] / [views.MLO] to use your own.
'''


def make_pelicano_case(out: Path, shared: Path, *, exam: str = "03") -> Path:
    """Crop the tumour breast of a Pelicano exam into ``out/pelicano_exam<exam>``."""
    folder = shared / "pelicano" / f"Exam_{exam}"
    src = next((p for p in sorted(folder.glob("*.zip")) if "simple" in p.name.lower()), None)
    if src is None:
        raise FileNotFoundError(f"{folder}: no *simple*.zip label map (is ../shared/data there?)")
    vol = read_label_map(src, label_dtype=np.int8)
    cropped, info = crop_tumour_breast(vol)
    case = out / f"pelicano_exam{exam}"
    write_label_map(cropped, case / "mri" / "labels.nii.gz")
    info.update(source=f"pelicano/Exam_{exam}/{src.name}", cropped_shape=list(cropped.shape),
                cropped_affine=cropped.affine.tolist(),
                label_voxel_counts={int(k): int(c) for k, c in zip(*np.unique(cropped.data, return_counts=True))})
    _io.write_json(case / "provenance.json", info)
    _io.write_text(case / "case.toml", pelicano_case_toml(exam, info["side"]))
    _io.write_text(case / "README.md", PELICANO_README.format(
        exam=exam, side_word="right" if info["side"] == "R" else "left", src_name=src.name,
        citation=PELICANO_CITATION))
    _io.write_text(case / "CITATION.md", PELICANO_CITATION)
    return case


def _size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 1e6


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "sample_cases")
    ap.add_argument("--shared-data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--only", choices=("phantom01", "phantom02", "pelicano_exam03"),
                    help="build one case (default: all three)")
    ap.add_argument("--no-mammograms", action="store_true",
                    help="the phantoms without their simulated mammograms (MRI part only, fast)")
    ap.add_argument("--truth-element-mm", type=float, default=None,
                    help="element size of the truth simulation's mesh (default: MammoTruthParams; "
                         "phantom02: 7.0)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    made = []
    for name, make, default_truth in (("phantom01", make_phantom01, None),
                                      ("phantom02", make_phantom02, phantom02_truth_params)):
        if args.only in (None, name):
            tp = None
            if args.truth_element_mm is not None:
                from regtrack.phantom.mammo_params import MammoTruthParams

                base = default_truth() if default_truth else MammoTruthParams()
                tp = dataclasses.replace(base, element_size_mm=args.truth_element_mm)
            made.append(make(args.out, mammograms=not args.no_mammograms, truth_params=tp))
    if args.only in (None, "pelicano_exam03"):
        made.append(make_pelicano_case(args.out, args.shared_data, exam="03"))
    for case in made:
        log.info("%s: %.2f MB", case, _size_mb(case))
    return 0


if __name__ == "__main__":
    sys.exit(main())
