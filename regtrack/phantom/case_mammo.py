"""The phantom case's mammograms: truth simulation -> DICOM MG + annotations + hidden truth.

:func:`make_case_mammograms` writes, inside a case folder,

* ``mammo/cc.dcm``, ``mammo/mlo.dcm``: DICOM MG for presentation (:mod:`.dicom_mg`);
* ``mammo/cc_tumour.json``, ``mammo/mlo_tumour.json``: the true projected tumour outline,
  ``{"points_rc": [[row, col], ...]}`` in the DICOM's own pixel grid;
* ``truth/mammo_truth.json``: the hidden ground truth (the pipeline never reads it):
  per view the applied rotation and shift, the nipple and the tumour centroid in the
  DICOM grid and in the canonical mm frame, the full plate -> image map, D and plate
  forces; plus the truth settings and the mismatch with the pipeline defaults.

It returns the ``[views.*]`` entries (with ``nipple_px``) for ``case.toml``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from regtrack import _io
from regtrack.imaging.volume import LabelVolume
from regtrack.mechanics.config import SolverOptions
from regtrack.phantom.dicom_mg import write_mg_dicom
from regtrack.phantom.mammo_params import MammoTruthParams
from regtrack.phantom.mammograms import SimulatedMammogram, simulate_mammogram
from regtrack.phantom.truth_sim import TruthSimulation, simulate_truth
from regtrack.views import VIEWS

log = logging.getLogger(__name__)

#: the settings the pipeline assumes by default (for the mismatch statement)
PIPELINE_DEFAULTS = {"tissue": "homogeneous, c1 0.54 kPa", "nu": 0.49, "friction": 0.1,
                     "target_nodes": 10000, "rotation_deg": 0.0, "target_D": {"CC": 0.38, "MLO": 0.28}}


def mismatch_statement(p: MammoTruthParams, sim: TruthSimulation) -> dict:
    """What differs between the truth simulation and the pipeline defaults."""
    m = sim.materials
    return {
        "tissue": (f"heterogeneous: fat {p.fat_c1_kpa} kPa, gland {p.gland_c1_kpa} kPa, transition "
                   f"{m['c1_kpa']['transition']:.3f} kPa by phantom label per element (volume-weighted "
                   f"mean {m['tissue_c1_mean_kpa']:.3f} kPa) vs homogeneous 0.54 kPa"),
        "nu": f"{p.nu} (shared bulk modulus; fat {m['nu_small_strain']['fat']:.4f}, gland "
              f"{m['nu_small_strain']['gland']:.4f}) vs 0.49",
        "friction": f"{p.friction} vs 0.1" + (
            " (frictionless truth: with 0.15 the standing-gravity step stalled, Newton residual "
            "stagnating near 1e-3 N)" if p.friction == 0 else ""),
        "mesh": (f"its own mesh, {sim.model.n_nodes} nodes (element size {p.element_size_mm} mm), vs the "
                 "pipeline's (about 10000 nodes by default; the sample case's case.toml sets 1500)"),
        "solver": (f"relative residual tolerance {p.force_tol:g} of the energy solver "
                   f"(pipeline default {SolverOptions().force_tol:g})"),
        "in_plane_rotation_deg": {"CC": p.rotation_cc_deg, "MLO": p.rotation_mlo_deg},
        "in_plane_shift_mm": {"CC": list(p.shift_cc_mm), "MLO": list(p.shift_mlo_mm)},
        "detector": (f"quantum noise (I0 = {p.quanta_per_pixel:g} quanta/pixel), fat/gland texture, "
                     f"skin line, {p.bits_stored}-bit, JPEG 2000 "
                     + ("lossless" if p.compression_ratio is None else f"lossy (target {p.compression_ratio:g}:1)")),
        "same_as_pipeline": "tumour c1 5.44 kPa, skin membrane, chest-wall layer 5 mm, protocol steps and plate geometry, "
                            "target D (CC 0.38, MLO 0.28), MLO plate angle 45 deg, orthogonal projection",
    }


def write_view(case: Path, sm: SimulatedMammogram, p: MammoTruthParams, *, case_id: str) -> dict:
    """Write one view's DICOM and tumour polygon; return its case.toml entry."""
    stem = sm.view.lower()
    dcm = write_mg_dicom(case / "mammo" / f"{stem}.dcm", sm.stored, view=sm.view,
                         laterality=sm.laterality, spacing_mm=sm.spacing_mm,
                         uid_seed=f"regtrack-{case_id}", patient=case_id, bits_stored=p.bits_stored,
                         compression_ratio=p.compression_ratio,
                         instance_number=1 if sm.view == "CC" else 2)
    poly = np.round(sm.tumour_rc, 2).tolist()
    _io.write_json(case / "mammo" / f"{stem}_tumour.json", {"points_rc": poly})
    return {"mammogram": f"mammo/{dcm.name}", "tumour_polygon": f"mammo/{stem}_tumour.json",
            "nipple_px": [round(float(v), 2) for v in sm.nipple_rc]}


def make_case_mammograms(case: str | Path, labels: LabelVolume, phantom_truth: dict, *,
                         params: MammoTruthParams | None = None, case_id: str = "phantom01",
                         views: tuple[str, ...] = VIEWS, progress: Any = None) -> dict:
    """Simulate, render and write the CC and MLO mammograms of a phantom case.

    Parameters
    ----------
    case : path-like
        Case folder (``mammo/`` and ``truth/`` are written in it).
    labels : LabelVolume
        The phantom label map (detailed Pelicano labels).
    phantom_truth : dict
        :func:`regtrack.phantom.make_phantom`'s truth (for the nipple and side).
    params : MammoTruthParams
    views : tuple of {"CC", "MLO"}
        Views to simulate (both for the sample case).
    progress : callable ``(step_name, t)``, optional
        Called after every converged solver increment.

    Returns
    -------
    dict
        ``{"views": {view: case.toml entry}, "truth": truth document}``.
    """
    p = params or MammoTruthParams()
    side = phantom_truth["params"]["side"]
    t0 = time.perf_counter()
    sim = simulate_truth(labels, phantom_truth["nipple_lps_mm"], p, side=side, views=views,
                         progress=progress)
    return write_case_mammograms(case, sim, p, case_id=case_id, t_start=t0)


def write_case_mammograms(case: str | Path, sim: TruthSimulation, p: MammoTruthParams, *,
                          case_id: str = "phantom01", t_start: float | None = None) -> dict:
    """Render and write the views of a finished truth simulation (see the module docstring)."""
    case = Path(case)
    t1 = time.perf_counter()
    entries, per_view = {}, {}
    for v, vt in sim.views.items():
        sm = simulate_mammogram(sim.model, vt.positions, v, p, plate_angle_deg=vt.plate_angle_deg,
                                gap_mm=vt.summary["plate_gap_mm"])
        entries[v] = write_view(case, sm, p, case_id=case_id)
        size = (case / entries[v]["mammogram"]).stat().st_size
        per_view[v] = {**sm.truth, "simulation": vt.summary, "steps": vt.steps,
                       "dicom": entries[v]["mammogram"], "dicom_bytes": size,
                       "compression_ratio_measured": float(sm.stored.size * 2 / size)}
    t2 = time.perf_counter()
    doc = {
        "note": "Hidden ground truth of the phantom mammograms: the pipeline never reads this file.",
        "generator": "regtrack.phantom.case_mammo.make_case_mammograms",
        "frames": {"dicom_rc": "row, col of the DICOM's own (stored) pixel grid, pixel centres at integers",
                   "canonical_mm": "regtrack.views canonical frame of the image as read: chest wall left, "
                                   "x = col * pixel_mm, y = row * pixel_mm of the canonical (flipped) image",
                   "rotation": "x_canonical = R(theta) (p_plate - n) + n + shift - offset, R = [[c, -s], [s, c]]"},
        "params": dataclasses.asdict(p),
        "mismatch_vs_pipeline_defaults": mismatch_statement(p, sim),
        "materials": sim.materials,
        "model": {"n_nodes": sim.model.n_nodes, "n_tets": sim.model.n_tets,
                  "nipple_node": int(sim.model.nipple), "frame": sim.model.frame.to_dict()},
        "views": per_view,
        "timing_s": {**sim.timing_s, "render_and_write": t2 - t1,
                     "total": t2 - (t_start if t_start is not None else t1)},
    }
    _io.write_json(case / "truth" / "mammo_truth.json", doc)
    log.info("phantom mammograms written to %s (render and write %.0f s)", case, t2 - t1)
    return {"views": entries, "truth": doc}
