"""MRI landmarks in a compressed breast, and back: ``regtrack track CASE --view V``.

For one simulated compression (``CC``, ``MLO`` or ``BIOPSY``, the latero-medial
compression of the prone breast in an MR biopsy coil; Azar et al. 2000, Chung et al.
2008) the case's mesh and simulation are taken from the stage cache of ``regtrack run``
(or computed and cached, :func:`open_compressed`); the FE deformation then maps MRI points
to the compressed state and back (:class:`~regtrack.tracking.deformation.DeformationMap`)
and resamples the MRI label map (and the MR series) into it (:mod:`.warp`).  No
mammogram is needed: everything stays in 3-D, in the MRI's patient frame (LPS, mm).

Outputs (:func:`write_points`, :func:`write_warped`, :func:`write_comparison`):
``points_<view>.json`` / ``points_<view>.csv`` (one row per point: name, direction, the
given position, the mapped position, the displacement, all LPS mm),
``labels_<view>.nii.gz`` / ``mri_<view>.nii.gz`` (and, for a DICOM input, the DICOM
series ``labels_<view>/`` / ``mri_<view>/`` in the source's frame of reference), and
``compare_<view>.json`` (the
simulated compression against an imaged compressed MRI, :mod:`.compare`).
"""

from __future__ import annotations

import csv
import io
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack._io import atomic_path, write_json
from regtrack.errors import TrackingError
from regtrack.tracking.deformation import DeformationMap
from regtrack.views import SIMULATED_VIEWS

log = logging.getLogger(__name__)


@dataclass
class CompressedState:
    """A case's model and one simulated compression of it."""

    case: Any
    view: str
    dmap: DeformationMap
    summary: dict
    model: Any = None  # BreastModel
    stage_keys: dict[str, str] = field(default_factory=dict)
    simulated_now: list[str] = field(default_factory=list)
    sim: Any = None  # pipeline.stages.SimOutput: the step records and result.vtu (the report)


def open_compressed(case_dir: str | Path, view: str, *, cache_dir: str | Path | None = None,
                    overrides: dict | None = None, simulate: bool = True,
                    progress: Callable[[str], None] | None = None) -> CompressedState:
    """The mesh and the ``view`` simulation of a case, from the stage cache or computed.

    The cache keys are those of ``regtrack run`` (for a view with a mammogram, the
    DICOM's plate gap and angle enter the protocol as there), so a case that was run is
    opened in seconds.  ``simulate=False`` raises :class:`TrackingError` instead of
    computing a missing stage.
    """
    from regtrack.case import load_case, resolve_configs
    from regtrack.pipeline import stages
    from regtrack.pipeline.geometry import apply_geometry
    from regtrack.pipeline.run import open_run

    v = str(view).upper()
    if v not in SIMULATED_VIEWS:
        raise TrackingError(f"--view {view}: unknown compression; use "
                            f"{', '.join(x.lower() for x in SIMULATED_VIEWS)}")
    case = load_case(case_dir)
    ctx = open_run(case, resolve_configs(case, overrides), cache_dir=cache_dir, progress=progress)
    mk = stages.mesh_key(ctx)
    real = v in case.views
    mesh = None
    if real and ctx.cache.has("mesh", mk):  # the DICOM's geometry enters the simulation key
        mesh = stages.mesh_stage(ctx)
        apply_geometry(ctx, mesh.model, (v,))
    todo = [] if ctx.cache.has("mesh", mk) else ["mesh"]
    if not ctx.cache.has("simulate", stages.simulate_key(ctx, mk, v)) or todo:
        todo.append(f"simulate_{v}")
    if todo and not simulate:
        raise TrackingError(f"case {case.id}: {', '.join(todo)} not in the cache "
                            f"{ctx.cache.root}; drop --no-simulate to compute them now")
    if todo:
        ctx.say(f"track: {', '.join(todo)} not in the cache {ctx.cache.root}; running them now "
                "(minutes; later calls re-use them)")
    if mesh is None:
        mesh = stages.mesh_stage(ctx)
    if real and not ctx.geometry:
        apply_geometry(ctx, mesh.model, (v,))
    sim = stages.simulate_stage(ctx, mesh, v)
    dmap = DeformationMap.from_model(mesh.model, sim.positions, view=v)
    return CompressedState(case, v, dmap, sim.summary, mesh.model,
                           {"mesh": mesh.key, f"simulate_{v}": sim.key}, todo, sim)


@dataclass(frozen=True)
class MappedPoints:
    """Points mapped between the MRI and a compressed state (LPS, mm)."""

    names: tuple[str, ...]
    direction: str  # "mri->compressed" or "compressed->mri"
    given_lps_mm: np.ndarray
    mapped_lps_mm: np.ndarray
    sigma_mm: np.ndarray | None = None  # 1-sigma of the mapped position (.sensitivity)
    sigma_terms_mm: dict | None = None
    sigma_sources: dict | None = None  # per term: "simulation" or "surrogate"

    @property
    def displacement_mm(self) -> np.ndarray:
        """(M,) distance between a point's MRI and compressed positions (mm)."""
        return np.linalg.norm(self.mapped_lps_mm - self.given_lps_mm, axis=1)

    def rows(self) -> list[dict]:
        mri, comp = ((self.given_lps_mm, self.mapped_lps_mm) if self.direction == "mri->compressed"
                     else (self.mapped_lps_mm, self.given_lps_mm))
        rows = [{"name": n, "direction": self.direction, "mri_lps_mm": mri[i].tolist(),
                 "compressed_lps_mm": comp[i].tolist(),
                 "displacement_mm": float(self.displacement_mm[i])}
                for i, n in enumerate(self.names)]
        if self.sigma_mm is not None:
            for i, r in enumerate(rows):
                r["sigma_mm"] = float(self.sigma_mm[i])
                terms = self.sigma_terms_mm or {}
                r["sigma_terms_mm"] = {k: float(v[i]) for k, v in terms.items()}
                if self.sigma_sources:
                    r["sigma_sources"] = dict(self.sigma_sources)
        return rows


def map_points(dmap: DeformationMap, names, lps_mm, *, inverse: bool = False) -> MappedPoints:
    """Forward (MRI -> compressed) or ``inverse`` map of named points (LPS mm)."""
    q = np.atleast_2d(np.asarray(lps_mm, float))
    names = tuple(names)
    out = dmap.inverse(q, names=names) if inverse else dmap.forward(q, names=names)
    return MappedPoints(names, "compressed->mri" if inverse else "mri->compressed", q, out)


def write_points(out: Path, state: CompressedState, mapped: list[MappedPoints], *,
                 surrogate: dict | None = None) -> list[Path]:
    """``points_<view>.json`` and ``.csv`` of the mapped points; ``surrogate``: the record
    (folder, validation error) of a surrogate that gave the uncertainty's terms."""
    out.mkdir(parents=True, exist_ok=True)
    stem = f"points_{state.view.lower()}"
    rows = [r for m in mapped for r in m.rows()]
    how = "1-sigma from c1, nu and the plate position (regtrack.tracking.sensitivity)"
    if surrogate is not None:
        how += ("; its terms predicted by the per-patient surrogate (the positions are the "
                "full simulation's)")
    doc = {"view": state.view, "frame": "patient LPS, mm (the MRI's frame of reference)",
           "compression": {k: state.summary.get(k) for k in ("protocol", "D", "T0_mm",
                                                              "plate_gap_mm", "upper_force_N",
                                                              "lower_force_N",
                                                              "force_imbalance_rel")},
           "stage_keys": state.stage_keys, "points": rows,
           "uncertainty": (how if any("sigma_mm" in r for r in rows)
                           else "not computed (give --uncertainty)")}
    if surrogate is not None:
        doc["surrogate"] = surrogate
    js = write_json(out / f"{stem}.json", doc)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["name", "direction", "mri_x", "mri_y", "mri_z", "compressed_x", "compressed_y",
                "compressed_z", "displacement_mm", "sigma_mm"])
    for r in rows:
        sigma = f"{r['sigma_mm']:.3f}" if "sigma_mm" in r else ""
        w.writerow([r["name"], r["direction"], *(f"{v:.3f}" for v in r["mri_lps_mm"]),
                    *(f"{v:.3f}" for v in r["compressed_lps_mm"]), f"{r['displacement_mm']:.3f}",
                    sigma])
    path = out / f"{stem}.csv"
    with atomic_path(path) as tmp:
        Path(tmp).write_text(buf.getvalue(), encoding="utf-8")
    return [js, path]


def write_warped(out: Path, state: CompressedState, *, series: bool = True,
                 progress: Callable[[str], None] | None = None, pseudonym: str | None = None,
                 keep_identifiers: bool = False) -> list[Path]:
    """The label map (and, with ``series`` and a case that has one, the MR series) warped
    into the compressed state, as ``labels_<view>.nii.gz`` / ``mri_<view>.nii.gz``.

    An input that is a DICOM series is also written as one, ``labels_<view>/`` /
    ``mri_<view>/`` (:func:`write_warped_dicom`): same study and frame of reference as the
    source, so a viewer overlays it on the MRI and on a compressed MRI of the session."""
    from regtrack.imaging.readers import (read_image_volume, read_label_map, write_image_volume,
                                          write_label_map)
    from regtrack.tracking.warp import warp_volume

    out.mkdir(parents=True, exist_ok=True)
    v = state.view.lower()
    say = progress or (lambda _m: None)
    pseudonym = pseudonym or f"regtrack-{v}"
    say(f"warp: label map into the {state.view} state")
    src = read_label_map(state.case.mri.labels)
    w = warp_volume(src, state.dmap)
    paths = [write_label_map(w.volume, out / f"labels_{v}.nii.gz")]
    if (src.meta or {}).get("format") == "dicom":
        paths += write_warped_dicom(w.volume, src, out / f"labels_{v}", view=state.view,
                                    what="label map", pseudonym=pseudonym,
                                    keep_identifiers=keep_identifiers)
    series_path = getattr(state.case.mri, "series", None)
    if series and series_path is not None:
        say(f"warp: MR series into the {state.view} state")
        src = read_image_volume(series_path)
        w = warp_volume(src, state.dmap, order=1)
        paths.append(write_image_volume(w.volume, out / f"mri_{v}.nii.gz"))
        if (src.meta or {}).get("format") == "dicom":
            paths += write_warped_dicom(w.volume, src, out / f"mri_{v}", view=state.view,
                                        what="MR series", pseudonym=pseudonym,
                                        keep_identifiers=keep_identifiers)
    return paths


def write_warped_dicom(vol, source, folder: Path, *, view: str, what: str, pseudonym: str,
                       keep_identifiers: bool = False) -> list[Path]:
    """``vol`` (warped from the DICOM series ``source``) as a DICOM series in ``folder``.

    The new series (new SeriesInstanceUID and SOPInstanceUIDs, ImageType DERIVED) keeps
    the source's StudyInstanceUID, FrameOfReferenceUID and patient module, and the grid's
    orientation and spacing (the warp keeps the source's, :mod:`.warp`); the identifiers
    follow the privacy rule: the PS3.15 basic profile with ``pseudonym`` unless
    ``keep_identifiers`` (:mod:`regtrack.privacy`).  Uncompressed (Explicit VR Little
    Endian), so any viewer reads it."""
    import pydicom

    from regtrack.imaging.dicom_series import write_dicom_series

    files = (source.meta or {}).get("files") or []
    if not files:
        raise TrackingError(f"{source.path}: the DICOM reader listed no slice files; cannot "
                            "copy the source's study and frame of reference")
    template = pydicom.dcmread(files[0], stop_before_pixels=True)
    if not template.get("FrameOfReferenceUID"):
        log.warning("%s has no FrameOfReferenceUID: the warped %s gets a new frame of "
                    "reference", Path(files[0]).name, what)
    if folder.is_dir():  # a previous run's slices: the new series replaces them
        for old in folder.glob("slice_*.dcm"):
            old.unlink()
    return write_dicom_series(vol, folder, patient=pseudonym, template=template,
                              deidentify=not keep_identifiers, transfer_syntax="explicit",
                              modality=str(template.get("Modality", "MR") or "MR"),
                              series_description=f"regtrack: {what} warped into the {view} "
                                                 "compression")


def write_comparison(out: Path, state: CompressedState, *, labels_path: str | Path | None,
                     predicted: MappedPoints | None = None, observed=None) -> tuple[Path, dict]:
    """``compare_<view>.json``: the simulated skin against the breast of the compressed MRI
    label map ``labels_path`` (surface distance, mm), and the ``predicted`` landmarks
    against the ``observed`` ones of the compressed MRI (matched by name)."""
    from regtrack.imaging.readers import read_label_map
    from regtrack.tracking.compare import landmark_distances, skin_distance

    doc: dict = {"view": state.view, "frame": "patient LPS, mm"}
    if labels_path is not None:
        sd = skin_distance(state.model, state.dmap.deformed, read_label_map(labels_path),
                           state.case.mri.scheme)
        doc["surface_distance"] = sd.to_dict()
    if predicted is not None and observed is not None:
        doc["landmarks"] = landmark_distances(predicted.names, predicted.mapped_lps_mm, observed)
    return write_json(out / f"compare_{state.view.lower()}.json", doc), doc
