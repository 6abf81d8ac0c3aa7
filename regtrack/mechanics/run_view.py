"""Case-level simulation of one mammographic view: model + protocol -> result files.

:func:`simulate_view` is what ``regtrack simulate CASE --view cc|mlo|biopsy`` calls: it reads the
case's ``[mechanics]``, ``[contact]`` and ``[protocol.<VIEW>]`` overrides, runs the
view's protocol (:mod:`.protocol_run`) on the model, and writes

* ``<id>_<view>.vtu``: the model with point data ``displacement`` (final) and
  ``displacement_<k>_<step>`` after every step (mm);
* ``<id>_<view>.json``: per step D, plate gap, plate positions and forces (N),
  penetration (mm), chest-wall reaction, solver statistics; plus the configs used;
* ``<id>_<view>_steps.png``: the compressed breast in the plate frame, step by step.

:func:`run_protocol_on_model` is the same without files (for studies and tests).
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack._io import atomic_path, write_json
from regtrack.config import parse_section, to_table
from regtrack.errors import ConfigError, ResultCheckError, SolverDidNotConvergeError
from regtrack.mechanics.contact import ContactConfig
from regtrack.mechanics.protocol import Protocol, protocol_for_view
from regtrack.mechanics.placement import BodySetup, skin_barrier
from regtrack.mechanics.protocol_run import ProtocolResult, ProtocolRunner
from regtrack.model.types import BreastModel

log = logging.getLogger(__name__)


@dataclass
class ViewResult:
    """Outcome of :func:`simulate_view`: the protocol result, files written, summary."""

    view: str
    result: ProtocolResult
    files: dict[str, Path] = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


def body_from_model(model: BreastModel, young_mpa: float, *, sliding: bool = False) -> BodySetup:
    """:class:`BodySetup` of a model whose tissue has the small-strain Young's modulus
    ``young_mpa`` (MPa; :attr:`.materials.ElementMaterials.tissue_young_mpa`).

    The plates' contact surface is every outer face of the model: the skin, the faces
    where the MRI's field of view or the fold cut the breast (on a CC these are the
    base's top and bottom, the first tissue the plates meet), and, with a ``sliding``
    chest wall (:mod:`.support`) whose nodes move along the wall, the chest-wall face.
    Only a clamped chest-wall face, which cannot move, is left out.  A plate opening is
    centred on the first tumour's centroid."""
    from regtrack.mechanics.meshes import boundary_faces

    surface = boundary_faces(model.points, np.asarray(model.tets)[:, :4])
    if not sliding:
        surface = surface[~np.asarray(model.fixed, bool)[surface].all(axis=1)]
    lesions = model.tumour_centroids()
    return BodySetup(points=model.points, tets=model.tets, surface=surface, fixed=model.fixed,
                     side=model.frame.side, young_mpa=young_mpa, clamped=not sliding,
                     target=lesions[min(lesions)] if lesions else None, axes=model.frame.axes)


def run_protocol_on_model(model: BreastModel, protocol: Protocol, *, mechanics: Any = None,
                          contact: ContactConfig | None = None, progress: Any = None
                          ) -> tuple[ProtocolResult, dict]:
    """Run ``protocol`` on ``model``; return the result and timings per phase (s)."""
    from regtrack.mechanics.config import MechanicsConfig
    from regtrack.mechanics.minimise import minimiser_from_problem
    from regtrack.mechanics.problem import build_problem

    mechanics = mechanics or MechanicsConfig()
    contact = contact or ContactConfig()
    t0 = time.perf_counter()
    problem = build_problem(model, mechanics, wall_layer_mm=contact.chest_wall_layer_mm)
    t1 = time.perf_counter()
    step_solver = minimiser_from_problem(problem, progress=progress)
    body = body_from_model(model, problem.mats.tissue_young_mpa, sliding=problem.support is not None)
    problem.self_contact = skin_barrier(body, contact)
    runner = ProtocolRunner(body, protocol, step_solver, config=contact)
    result = runner.run()
    result.materials = problem.tissue_c1.info
    if problem.self_contact is not None:
        result.self_contact_reach_mm = problem.self_contact.dhat
    t2 = time.perf_counter()
    return result, {"setup_s": t1 - t0, "protocol_s": t2 - t1, "total_s": t2 - t0}


def _section(case: Any, name: str, cls: type, where: str):
    ov = getattr(case, "overrides", {}).get(name)
    if ov is None:
        return cls()
    if getattr(ov, "config", None) is not None:
        return ov.config
    obj, problems, _ = parse_section(cls, ov.table, where=where)
    if problems:
        raise ConfigError("; ".join(problems))
    return obj


def simulate_view(case: Any, model: BreastModel, view: str, *, out_dir: str | Path,
                  mechanics: Any = None, contact: ContactConfig | None = None,
                  protocol: Protocol | None = None, progress: Any = None,
                  partial_dir: str | Path | None = None) -> ViewResult:
    """Simulate the ``view`` ("CC"/"MLO") mammography of a case and write the result files.

    Explicit ``mechanics``/``contact``/``protocol`` replace the case's overrides.  A run
    that stops keeps its balanced steps in ``partial_dir`` (default ``out_dir``; a caller
    whose ``out_dir`` is discarded on failure, as the stage cache's temporary folder is,
    gives a lasting one) and names the file in its error.
    """
    from regtrack.mechanics.config import MechanicsConfig

    v = str(view).upper()
    where = str(getattr(case, "toml_path", "case.toml"))
    mechanics = mechanics or _section(case, "mechanics", MechanicsConfig, f"{where} [mechanics]")
    contact = contact or _section(case, "contact", ContactConfig, f"{where} [contact]")
    if protocol is None:
        ov = getattr(case, "overrides", {}).get(f"protocol.{v}")
        protocol = protocol_for_view(v, ov.table if ov is not None else None, where=where,
                                     base_dir=getattr(case, "root", None))
    case_id = getattr(case, "id", "model")
    try:
        result, timing = run_protocol_on_model(model, protocol, mechanics=mechanics, contact=contact,
                                               progress=progress)
    except (SolverDidNotConvergeError, ResultCheckError) as err:
        _keep_partial(err, model, Path(partial_dir or out_dir), f"{case_id}_{v.lower()}_partial")
        raise
    files = write_outputs(result, model, Path(out_dir), stem=f"{case_id}_{v.lower()}",
                          configs={"mechanics": to_table(mechanics), "contact": to_table(contact)},
                          timing=timing)
    return ViewResult(view=v, result=result, files=files, summary=summarise(result, timing))


def _keep_partial(err: Exception, model: BreastModel, out_dir: Path, stem: str) -> None:
    """Write the balanced steps of a stopped run (``err.last_converged``, a
    :class:`ProtocolResult`) as ``<stem>.vtu/.json/_steps.png`` and name them in the error's
    message, so that nothing computed is lost; the caller does not go on with them."""
    partial = getattr(err, "last_converged", None)
    if not isinstance(partial, ProtocolResult) or not partial.steps:
        return
    try:
        files = write_outputs(partial, model, out_dir, stem=stem)
    except OSError as exc:
        log.warning("could not keep the balanced steps of the stopped run: %s", exc)
        return
    err.args = (f"{err.args[0] if err.args else err}; the {len(partial.steps)} balanced "
                f"step(s) before it are kept in {files['vtu']}",)


def summarise(result: ProtocolResult, timing: dict | None = None) -> dict:
    """Headline figures of a run: D, plate force, penetration, steps, iterations, time.

    ``upper_edge_force_N``: the part of the upper plate force carried by the skin that lay
    within ``[contact] edge_band_mm`` in front of the plate's chest-wall edge (15 mm of the
    chest wall at the defaults).  That tissue is attached to the fixed chest wall; on
    Pelicano exam 10 CC it carries 87 to 93 % of the plate force: 39 N on 1.9k nodes and
    81 N on 8.9k, while the rest of the breast carries 5.4 to 6.6 N on every mesh
    (pipelines/mesh_convergence.py).  ``upper_body_force_N`` is
    the rest, ``upper_force_N - upper_edge_force_N``: the force of the breast between the
    plates, the part that does not grow with mesh refinement.  ``behind_chest_wall_mm``: the
    deepest any node ended a step behind the chest-wall plane
    (:func:`regtrack.mechanics.placement.behind_chest_wall`); ``skin_overlap_mm``: the
    deepest any skin node ended a step inside the tissue, and ``skin_overlap_nodes`` how many
    at the last step (:func:`regtrack.mechanics.overlap.overlaps`); ``self_contact_reach_mm``:
    the self-contact barrier's reach (:func:`regtrack.mechanics.placement.skin_barrier`;
    None when off); ``warnings``: every
    step's warnings (``[contact] behind_wall_warn_mm``, ``skin_overlap_warn_mm``).
    ``force_imbalance_rel``: the largest over the steps of the global force imbalance
    (the residual's resultant over the free nodes) relative to the step's largest load
    (:func:`regtrack.mechanics.problem.force_balance`; a step above ``[mechanics.solver]
    stall_force_tol`` is refused), None without fixed nodes."""
    behind = [s.behind_chest_wall_mm for s in result.steps if s.behind_chest_wall_mm is not None]
    overlap = [s.skin_overlap_mm for s in result.steps if s.skin_overlap_mm is not None]
    balance = [s.solver["force_balance"]["relative"] for s in result.steps
               if isinstance(s.solver.get("force_balance"), dict)]
    last = result.steps[-1]
    # a protocol with no plate step (gravity only) has no plate force
    up, low = (last.contact.get(k) or {} for k in ("upper", "lower"))
    upper, edge = up.get("normal_force_N"), up.get("edge_normal_force_N")
    return {"protocol": result.protocol.name, "view": result.protocol.view,
            "complete": result.complete, "D": last.D, "D_mean": last.D_mean,
            "plate_gap_mm": last.gap_mm, "T0_mm": last.T0_mm,
            "upper_force_N": upper,
            "lower_force_N": low.get("normal_force_N"),
            "upper_edge_force_N": edge,
            "upper_body_force_N": None if edge is None or upper is None else upper - edge,
            "max_penetration_mm": max(s.max_penetration_mm for s in result.steps),
            "increments": sum(s.solver.get("increments", 0) for s in result.steps),
            "iterations": sum(s.solver.get("iterations", 0) for s in result.steps),
            "cutbacks": sum(s.solver.get("cutbacks", 0) for s in result.steps),
            "behind_chest_wall_mm": max(behind) if behind else None,
            "skin_overlap_mm": max(overlap) if overlap else None,
            "skin_overlap_nodes": last.skin_overlap_nodes,
            "self_contact_reach_mm": result.self_contact_reach_mm,
            "force_imbalance_rel": max(balance) if balance else None,
            "warnings": [w for s in result.steps for w in s.warnings],
            "tissue": result.materials, "timing_s": timing or {}}


def write_outputs(result: ProtocolResult, model: BreastModel, out_dir: Path, *, stem: str,
                  configs: dict | None = None, timing: dict | None = None) -> dict[str, Path]:
    """Write the .vtu, .json and .png of a protocol result (atomically)."""
    import meshio

    from regtrack.mechanics.pictures import protocol_figure
    from regtrack.model.checks import cut_faces

    out_dir.mkdir(parents=True, exist_ok=True)
    pdata: dict[str, np.ndarray] = {"fixed": model.fixed.astype(np.int8)}
    for k, st in enumerate(result.steps):
        pdata[f"displacement_{k + 1}_{re.sub(r'[^A-Za-z0-9]+', '_', st.name)}"] = st.u
    pdata["displacement"] = result.u
    mesh = meshio.Mesh(model.points, [("tetra", model.tets), ("triangle", model.skin)],
                       point_data=pdata,
                       cell_data={"region": [model.region, np.full(len(model.skin), 3)]})
    vtu = out_dir / f"{stem}.vtu"
    with atomic_path(vtu) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")
    doc = {"summary": summarise(result, timing), "protocol": result.protocol.to_dict(),
           "plate_frame": result.plate_frame, "steps": [s.to_dict() for s in result.steps],
           "config": configs or {}, "error": result.error}
    js = write_json(out_dir / f"{stem}.json", doc)
    png = protocol_figure(out_dir / f"{stem}_steps.png", model.points, model.skin, result.steps,
                          result.plate_frame, title=f"{stem}: {result.protocol.name}",
                          cut=cut_faces(model.tets, model.skin, model.fixed))
    return {"vtu": vtu, "json": js, "png": png}
