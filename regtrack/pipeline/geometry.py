"""Each view's acquisition geometry: the DICOM's, case.toml's, or the default, and which.

For every view with a real mammogram, :func:`resolve_geometry` decides (case.toml first,
then the DICOM header when its value is plausible, then the default):

* the **final plate gap**: a target of ``[protocol.<VIEW>]`` (``target_D``,
  ``target_gap_mm``, ``target_force_N``) wins; else BodyPartThickness becomes the
  protocol's ``target_gap_mm`` (the compression degree ``D`` is then an output); else the
  protocol's own target (the paper's ``D``).  A thickness that would compress the model by
  less than 5 % or more than 75 % of its thickness along the plate normal is dropped with
  a warning (the breast on the MRI and on the mammogram are the same breast);
* the **MLO plate angle**: ``[protocol.MLO] angle_deg``; else |PositionerPrimaryAngle|;
  else the protocol's 45 deg;
* the **projection** of the virtual mammogram (``[virtual] projection``): ``orthogonal``
  (the paper's), ``cone`` or ``auto`` (default: a cone beam when the header gives the
  source distances, else orthogonal).  An explicit ``[virtual] source_to_image_mm`` wins
  over the header.  The source is ``SSD`` (DistanceSourceToPatient, or
  DistanceSourceToDetector / EstimatedRadiographicMagnificationFactor) above the breast
  support; the image plane is the plane at which the real image's pixel spacing holds
  (magnification ``r``, :attr:`DicomGeometry.spacing_magnification`: the detector when
  ``r = 1``), so the point-source map of :mod:`regtrack.virtual.xray` gets
  ``source_to_image_mm = SID / r`` and ``detector_gap_mm = SID / r - SSD``.  A point at
  height ``h`` above the support and in-plane offset ``X`` from the source's foot lands at
  ``X (SID / r) / (SSD - h)``;
* the **compression force** of the header is only reported (``dicom_force_N`` beside the
  simulated ``force_N``), with its unit check.

Every decision is recorded with its source (``"DICOM BodyPartThickness (0018,11A0)"``,
``"case.toml [protocol.CC] target_D"``, ``"default ..."``) for the provenance and the report.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from regtrack.errors import ConfigError
from regtrack.imaging.mammogram.geometry import DicomGeometry, read_geometry_file

log = logging.getLogger(__name__)

TARGETS = ("target_D", "target_gap_mm", "target_force_N")
#: accepted compression of the model by a DICOM thickness, 1 - gap / (model thickness)
MIN_DEGREE, MAX_DEGREE = 0.05, 0.75


@dataclass
class GeometryInputs:
    """What :func:`resolve_geometry` reads and writes: the case (its views and where its
    case.toml lies), the ``[protocol.<VIEW>]`` tables (the DICOM's choices are written into
    them), the base virtual-mammogram config and the identifier scrubber of the log lines
    (None: no identifiers to scrub)."""

    case: Any
    protocol_tables: dict
    virtual: Any = None
    ids: Any = None


@dataclass
class Choice:
    """One geometry value and where it came from."""

    value: Any
    source: str
    unit: str = ""

    def to_dict(self) -> dict:
        return {"value": self.value, "unit": self.unit, "source": self.source}


@dataclass
class ViewGeometry:
    """The geometry decided for one view (see the module docstring)."""

    view: str
    dicom: DicomGeometry
    gap: Choice
    angle: Choice
    projection: Choice
    force: Choice
    virtual: Any = None                 # VirtualConfig of this view
    protocol_table: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def gap_source(self) -> str:
        """``"dicom"``, ``"case.toml"`` or ``"default"``: who set the final plate gap."""
        s = self.gap.source
        return "dicom" if s.startswith("DICOM") else "case.toml" if s.startswith("case") else "default"

    def row(self) -> dict:
        """Columns of the metrics row."""
        return {"dicom_thickness_mm": self.dicom.thickness_mm,
                "gap_source": self.gap_source, "dicom_force_N": self.dicom.force_N,
                "plate_angle_deg": self.angle.value,
                "projection": "orthogonal" if self.projection.value == "orthogonal" else "cone"}

    def to_dict(self) -> dict:
        return {"final_plate_gap": self.gap.to_dict(), "plate_angle": self.angle.to_dict(),
                "projection": self.projection.to_dict(), "compression_force": self.force.to_dict(),
                "dicom": self.dicom.to_dict(), "warnings": self.warnings}


def _model_thickness(model, view: str, side: str, angle: float | None) -> float:
    """Extent (mm) of the reference model along the view's plate normal: about the
    uncompressed thickness T0 the protocol measures at first contact."""
    from regtrack.virtual.frames import plate_frame

    h = np.asarray(model.points, float) @ plate_frame(view, side, angle_deg=angle).normal
    return float(h.max() - h.min())


def _base_protocol(ctx, view: str, table: dict):
    """The view's protocol as case.toml gives it, without a target override."""
    from regtrack.mechanics.protocol import protocol_for_view

    rest = {k: v for k, v in table.items() if k not in TARGETS}
    return protocol_for_view(view, rest or None, where=str(ctx.case.toml_path),
                             base_dir=ctx.case.root)


def _default_target(proto) -> Choice:
    last = [s for s in proto.steps if s.action == "move_plate" and s.plate == "upper"][-1:]
    if last and last[0].target_D is not None:
        return Choice(None, f"default (protocol {proto.name}: D = {last[0].target_D:g})")
    return Choice(None, f"default (protocol {proto.name})")


def _gap(ctx, view: str, table: dict, g: DicomGeometry, model, angle, warn) -> Choice:
    given = [k for k in TARGETS if table.get(k) is not None]
    if given:
        k = given[0]
        return Choice(table[k], f"case.toml [protocol.{view}] {k}",
                      {"target_D": "", "target_gap_mm": "mm", "target_force_N": "N"}[k])
    proto = _base_protocol(ctx, view, table)
    if g.thickness_mm is None:
        return _default_target(proto)
    if not any(s.action == "move_plate" and s.plate == "upper" for s in proto.steps):
        warn(f"[views.{view}] BodyPartThickness (0018,11A0) = {g.thickness_mm:g} mm not used: "
             f"protocol {proto.name} moves no upper plate")
        return _default_target(proto)
    if model is not None:
        T = _model_thickness(model, view, model.frame.side, angle)
        D = 1.0 - g.thickness_mm / T
        if not MIN_DEGREE <= D <= MAX_DEGREE:
            warn(f"[views.{view}] BodyPartThickness (0018,11A0) = {g.thickness_mm:g} mm would "
                 f"compress the {T:.0f} mm thick model by D = {D:.2f} (accepted "
                 f"{MIN_DEGREE:g}-{MAX_DEGREE:g}); ignored, the protocol's target is used")
            return _default_target(proto)
    table["target_gap_mm"] = float(g.thickness_mm)
    return Choice(float(g.thickness_mm), "DICOM BodyPartThickness (0018,11A0)", "mm")


def _angle(view: str, table: dict, g: DicomGeometry) -> Choice:
    if table.get("angle_deg") is not None:
        return Choice(float(table["angle_deg"]), f"case.toml [protocol.{view}] angle_deg", "deg")
    if view == "MLO" and g.angle_deg is not None:
        table["angle_deg"] = float(g.angle_deg)
        sign = "" if g.angle_raw is None or g.angle_raw >= 0 else \
            f", magnitude of {g.angle_raw:g}"
        return Choice(float(g.angle_deg), f"DICOM PositionerPrimaryAngle (0018,1510){sign}",
                      "deg")
    return Choice(45.0 if view == "MLO" else 0.0, "default (protocol)", "deg")


def _projection(view: str, cfg, g: DicomGeometry) -> tuple[Choice, Any]:
    """The view's VirtualConfig and how its projection was chosen."""
    mode = getattr(cfg, "projection", "auto")
    if mode == "orthogonal":
        cfg = dataclasses.replace(cfg, source_to_image_mm=0.0)
        return Choice("orthogonal", "config [virtual] projection = orthogonal"), cfg
    if cfg.source_to_image_mm > 0:
        return (Choice(f"cone beam, image plane {cfg.source_to_image_mm:g} mm from the source",
                       "config [virtual] source_to_image_mm"), cfg)
    if g.sid_mm is not None:
        r = g.spacing_magnification
        sid_eff = g.sid_mm / r
        if g.ssd_mm is not None:
            gap = max(sid_eff - g.ssd_mm, 0.0)
            how = f"DICOM DistanceSourceToDetector (0018,1110) and {g.ssd_from}"
        else:
            gap = cfg.detector_gap_mm
            how = ("DICOM DistanceSourceToDetector (0018,1110); support-to-detector gap "
                   f"{gap:g} mm from [virtual] detector_gap_mm")
        cfg = dataclasses.replace(cfg, source_to_image_mm=float(sid_eff),
                                  detector_gap_mm=float(min(gap, 200.0)))
        plane = "detector" if r == 1.0 else f"plane of the pixel spacing (magnification {r:.3f})"
        return (Choice(f"cone beam, SID {g.sid_mm:g} mm, source {sid_eff - gap:g} mm above the "
                       f"support, image on the {plane}", how), cfg)
    if mode == "cone":
        raise ConfigError(f"[virtual] projection = \"cone\" for the {view} view, but its DICOM has "
                          "no plausible DistanceSourceToDetector (0018,1110): set [virtual] "
                          "source_to_image_mm (about 650 mm) or projection = \"orthogonal\"")
    return Choice("orthogonal", "default (no DICOM source distances)"), cfg


def resolve_geometry(ctx: GeometryInputs, model=None, *, views=None) -> dict[str, ViewGeometry]:
    """Decide each real view's geometry; write the DICOM's choices into
    ``ctx.protocol_tables`` (a copy per view) and return them by view.

    ``model`` (the reference BreastModel) is used to check a DICOM thickness against the
    breast's own thickness; without it the thickness is checked against its range only.
    ``views``: the views to resolve (default every view of the case with a mammogram).
    Warnings are logged (one line each, naming the tag) and recorded.
    """
    out: dict[str, ViewGeometry] = {}
    base_virtual = ctx.virtual
    if base_virtual is None:
        from regtrack.virtual.config import VirtualConfig

        base_virtual = VirtualConfig()
    for view, vi in ctx.case.views.items():
        if views is not None and view not in views:
            continue
        warnings: list[str] = []

        def warn(msg: str, _w=warnings) -> None:
            _w.append(msg)

        name = f"[views.{view}] {vi.mammogram.name}"
        g = read_geometry_file(vi.mammogram, name=name, view=view)
        warnings += g.warnings
        table = dict(ctx.protocol_tables.get(view) or {})
        angle = _angle(view, table, g)
        gap = _gap(ctx, view, table, g, model, angle.value if view == "MLO" else None, warn)
        proj, vcfg = _projection(view, base_virtual, g)
        force = Choice(g.force_N, "DICOM CompressionForce (0018,11A2), unit " + g.force_unit
                       + "; reported only, not used as a load", "N") if g.force_N is not None \
            else Choice(None, "absent or implausible in the DICOM")
        for w in warnings:
            log.warning("%s", ctx.ids.scrub(w) if ctx.ids is not None else w)
        ctx.protocol_tables[view] = table
        out[view] = ViewGeometry(view, g, gap, angle, proj, force, vcfg, table, warnings)
    return out


def apply_geometry(ctx, model, views) -> None:
    """Resolve the real views' geometry (:func:`resolve_geometry`) into ``ctx.geometry`` and
    hand the resulting ``[protocol.<VIEW>]`` tables to ``ctx.configs`` (the protocols are
    parsed again, so the simulations and their cache keys follow the DICOM)."""
    tables = {v: dict(t) for v, t in ctx.configs.protocol_tables.items()}
    inputs = GeometryInputs(ctx.case, tables, ctx.configs.virtual, ctx.ids)
    ctx.geometry = resolve_geometry(inputs, model, views=views)
    ctx.configs = ctx.configs.with_protocol_tables(ctx.case, {v: tables[v] for v in ctx.geometry})
