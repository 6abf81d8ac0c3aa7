"""Ground-truth compression of the phantom: the CC and MLO protocols with the truth settings.

The pipeline will model the phantom with homogeneous tissue; the truth is simulated with
heterogeneous tissue instead (:class:`~regtrack.phantom.mammo_params.MammoTruthParams`):
each tetrahedron takes the neo-Hookean c1 of the phantom label at its centroid,

.. math:: W_e = c_{1,e} (\\bar I_1 - 3) + \\frac{K}{2} (J - 1)^2,
          \\qquad K = \\frac{2 \\bar\\mu (1 + \\nu)}{3 (1 - 2 \\nu)},\\quad \\bar\\mu = 2 \\bar c_1,

with one bulk modulus ``K`` for all non-tumour tissue, set by the volume-weighted mean
``c1`` and the truth ``nu``.  A single ``K`` keeps fat and gland in one group of the
average-nodal-pressure tetrahedra (the locking-free formulation averages the volume
change per node and material group; a patchwork of element-sized groups would lock
again); the small-strain Poisson ratio of each class is then
``nu_e = (3K - 2 mu_e) / (2 (3K + mu_e))`` (recorded).  Everything else (gravity
unloading, plates, friction, compression to the target D) is the project's own protocol
engine (:mod:`regtrack.mechanics.protocol_run`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from regtrack.imaging.volume import LabelVolume
from regtrack.model.types import TUMOUR, BreastModel
from regtrack.phantom.make import FAT_LABELS, GLAND_LABELS, TRANSITION
from regtrack.phantom.mammo_params import MammoTruthParams
from regtrack.views import VIEWS

log = logging.getLogger(__name__)


@dataclass
class ViewTruth:
    """Truth compression of one view (mm, model frame)."""

    view: str
    positions: np.ndarray  # (N, 3) deformed node positions
    plate_angle_deg: float
    summary: dict  # D, T0, gap, plate forces, penetration, iterations, time
    steps: list[dict] = field(default_factory=list)


@dataclass
class TruthSimulation:
    """The truth model and its compressed states."""

    model: BreastModel
    views: dict[str, ViewTruth]
    materials: dict
    timing_s: dict


def element_c1_kpa(model: BreastModel, p: MammoTruthParams) -> np.ndarray:
    """c1 (kPa) of every tetrahedron from its phantom label (see the module docstring): the
    mechanics core's fat/gland map (``tissue_model = "heterogeneous"``) on the phantom's
    labels, and the tumour's c1 on the tumour."""
    from regtrack.mechanics.config import MechanicsConfig
    from regtrack.mechanics.materials import tissue_stiffness

    if model.tissue_label is None:
        raise ValueError("truth model has no tissue_label: mesh it with regtrack.model.build.build_model")
    cfg = MechanicsConfig(tissue_model="heterogeneous", fat_c1_kpa=p.fat_c1_kpa, gland_c1_kpa=p.gland_c1_kpa,
                          fat_labels=FAT_LABELS, gland_labels=GLAND_LABELS, transition_labels=(TRANSITION,))
    c1 = tissue_stiffness(model.region, model.tissue_label, model.tet_volumes(), cfg).c1_kpa.copy()
    c1[model.region == TUMOUR] = p.tumour_c1_kpa
    return c1


def material_summary(model: BreastModel, c1_kpa: np.ndarray, p: MammoTruthParams) -> dict:
    """Volume fractions, mean c1 and the per-class Poisson ratio under the shared K."""
    vol = np.abs(model.tet_volumes())
    lab = model.tissue_label
    tissue = model.region != TUMOUR
    c1_mean = float(np.sum(c1_kpa[tissue] * vol[tissue]) / np.sum(vol[tissue]))
    mu_mean = 2 * c1_mean
    k = 2 * mu_mean * (1 + p.nu) / (3 * (1 - 2 * p.nu))

    def nu_of(c1: float) -> float:
        mu = 2 * c1
        return float((3 * k - 2 * mu) / (2 * (3 * k + mu)))

    frac = {name: float(vol[tissue & np.isin(lab, labs)].sum() / vol[tissue].sum())
            for name, labs in (("gland", GLAND_LABELS), ("transition", (TRANSITION,)),
                               ("fat", FAT_LABELS))}
    frac["other (skin)"] = 1.0 - sum(frac.values())
    return {"c1_kpa": {"fat": p.fat_c1_kpa, "gland": p.gland_c1_kpa,
                       "transition": 0.5 * (p.fat_c1_kpa + p.gland_c1_kpa), "tumour": p.tumour_c1_kpa},
            "tissue_volume_fraction": frac, "tissue_c1_mean_kpa": c1_mean,
            "tissue_bulk_modulus_kpa": k, "nu_mean_material": p.nu,
            "nu_small_strain": {"fat": nu_of(p.fat_c1_kpa), "gland": nu_of(p.gland_c1_kpa)},
            "friction": p.friction, "formulation": "p1-anp (one ANP group for all tissue, one for the tumour)"}


def build_truth_model(labels: LabelVolume, nipple_lps, p: MammoTruthParams, *, side: str = "R",
                      progress: Any = None) -> BreastModel:
    """Mesh the phantom label map finer than the pipeline default (``p.element_size_mm``)."""
    from regtrack.model.build import build_model
    from regtrack.model.config import MeshConfig
    from regtrack.model.labels import PRESETS

    return build_model(labels, scheme=PRESETS["pelicano-detailed"],
                       config=MeshConfig(element_size_mm=p.element_size_mm,
                                         surface_step_vox=p.surface_step_vox), side=side,
                       nipple_lps=np.asarray(nipple_lps, float), progress=progress)


def simulate_view(model: BreastModel, view: str, p: MammoTruthParams, *, progress: Any = None) -> ViewTruth:
    """Run the shipped protocol of ``view`` to the truth D with the truth materials."""
    from regtrack.mechanics.config import MechanicsConfig, SolverOptions
    from regtrack.mechanics.contact import ContactConfig
    from regtrack.mechanics.materials import KPA
    from regtrack.mechanics.problem import build_problem
    from regtrack.mechanics.protocol import protocol_for_view
    from regtrack.mechanics.minimise import minimiser_from_problem
    from regtrack.mechanics.protocol_run import ProtocolRunner
    from regtrack.mechanics.run_view import body_from_model, summarise

    c1 = element_c1_kpa(model, p)
    mats = material_summary(model, c1, p)
    cfg = MechanicsConfig(tissue_c1_kpa=mats["tissue_c1_mean_kpa"], tumour_c1_kpa=p.tumour_c1_kpa, nu=p.nu,
                          skin_enabled=p.skin_membrane,
                          solver=SolverOptions(force_tol=p.force_tol,
                                               initial_increment=p.initial_increment))
    t0 = time.perf_counter()
    problem = build_problem(model, cfg, wall_layer_mm=p.chest_wall_layer_mm)
    # heterogeneous deviatoric stiffness; K (hence the ANP groups) stays that of the mean c1
    problem.mats = dataclasses.replace(problem.mats, c1=c1 * KPA)
    protocol = protocol_for_view(view, {"target_D": p.target_D(view)}, where="phantom truth")
    body = body_from_model(model, problem.mats.tissue_young_mpa, sliding=problem.support is not None)
    runner = ProtocolRunner(body, protocol, minimiser_from_problem(problem, progress=progress),
                            config=ContactConfig(friction=p.friction, chest_wall_contact=False))
    result = runner.run()
    t1 = time.perf_counter()
    summary = summarise(result, {"total_s": t1 - t0})
    log.info("truth %s: D = %.3f, plate force %.1f N, %d iterations, %.0f s", view, summary["D"],
             summary["upper_force_N"], summary["iterations"], t1 - t0)
    return ViewTruth(view=view, positions=model.points + result.u,
                     plate_angle_deg=float(result.plate_frame["angle_deg"]), summary=summary,
                     steps=[s.to_dict() for s in result.steps])


def simulate_truth(labels: LabelVolume, nipple_lps, p: MammoTruthParams, *, side: str = "R",
                   views=VIEWS, progress: Any = None) -> TruthSimulation:
    """Mesh the phantom and compress it in each view with the truth settings."""
    t0 = time.perf_counter()
    model = build_truth_model(labels, nipple_lps, p, side=side)
    t1 = time.perf_counter()
    out = {v: simulate_view(model, v, p, progress=progress) for v in views}
    t2 = time.perf_counter()
    mats = material_summary(model, element_c1_kpa(model, p), p)
    return TruthSimulation(model=model, views=out, materials=mats,
                           timing_s={"mesh": t1 - t0, "mechanics": t2 - t1})
