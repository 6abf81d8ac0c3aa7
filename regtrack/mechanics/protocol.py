"""Mammography protocols as data: the TOML schema, the shipped protocols and overrides.

A protocol is an ordered list of steps (Lapuebla-Ferri et al., four-step protocol)::

    name = "cc"
    view = "CC"                  # plate orientation (regtrack.virtual.frames.plate_frame)
    angle_deg = 0.0              # optional: plate rotation about the AP axis (degrees)

    [plates]                     # geometry of both plates (mm)
    edge_radius_mm = 10.0        # rounded (cylindrical) chest-wall edge
    posterior_edge_mm = 0.0      # chest-wall edge, anterior to the chest-wall plane
    clearance_mm = 2.0           # plates' distance from the breast at the first plate step
    # window_mm = [40.0, 40.0]   # an opening in one plate (the biopsy grid's compression
    # window_plate = "lower"     # window), centred on the lesion's projection

    [[steps]]
    name = "gravity-unloading"
    action = "gravity"           # add a named gravity load: direction x factor g
    load = "prone-unloading"
    direction = [0.0, 1.0, 0.0]
    frame = "patient"            # direction in the MRI's LPS axes (default "model")
    factor = 1.0

    [[steps]]
    action = "move_plate"        # plate "lower" / "upper" moved along its normal
    plate = "lower"
    to = "contact"               # contact | degree | gap | force | position
    # target_D = 0.38 (degree) | target_gap_mm = 45 (gap) | target_force_N = 100 (force)
    # | distance_mm = 30 (position: travel along the plate normal)

    [[steps]]
    action = "remove_gravity"    # or "hold"
    load = "prone-unloading"

Gravity loads add up: the body force at any time is ``rho g sum_k factor_k d_k`` with
``g = 9.81 m/s^2`` and ``d_k`` the unit directions of the active loads.  A direction is
given in the model frame (``x`` the chest-wall normal, ``y`` superior) or, with
``frame = "patient"``, in the MRI's LPS axes.  Gravity is a patient-frame load: the MRI is
prone, so its gravity is LPS anterior ``(0, -1, 0)`` and the unloading step applies
``(0, 1, 0)``; standing gravity is LPS inferior ``(0, 0, -1)`` for both views (the MLO
rotates the plates, not the patient).  In the model frame these would turn with the
chest wall, which faces 17-27 degrees laterally of anterior on the Pelicano breasts.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from regtrack.config import param, parse_section
from regtrack.errors import ConfigError
from regtrack.views import SIMULATED_VIEWS

ACTIONS = ("gravity", "remove_gravity", "move_plate", "hold")
FRAMES = ("model", "patient")
PLATE_MODES = ("contact", "degree", "gap", "force", "position")
PLATES = ("lower", "upper")
G_STANDARD = 9.81  # m/s^2


@dataclass(frozen=True)
class PlateGeometry:
    """Geometry of the compression plates (``[plates]`` of a protocol)."""

    edge_radius_mm: float = param(10.0, "mm", "radius of the rounded chest-wall edge", gt=0, le=200)
    posterior_edge_mm: float = param(0.0, "mm", "chest-wall edge of the plates: where their "
                                     "flat face ends, anterior to the chest-wall plane (0: the "
                                     "face reaches the wall, as a paddle's does). With the "
                                     "chest-wall contact on, 0 < value <= "
                                     "edge_radius_mm is refused: the rounded edge would make an "
                                     "acute wedge with the wall (regtrack.mechanics.placement)",
                                     ge=-200, le=200)
    clearance_mm: float = param(2.0, "mm", "distance of the plates from the breast when "
                                "they are placed, at the first plate step (the breast "
                                "hangs free before it)",
                                ge=0, le=100)
    window_mm: list[float] | None = param(None, "mm", "[along e_x, across] opening of the grid "
                                          "plate, centred on the lesion (none: solid plates)")
    window_plate: str = param("lower", "", "the plate with the opening", choices=PLATES)

    def problems(self) -> list[str]:
        w = self.window_mm
        if w is not None and (len(w) != 2 or not all(5.0 <= v <= 300.0 for v in w)):
            return [f"window_mm = {list(w)}: give [width, height] of the opening, each "
                    "5 to 300 mm"]
        return []


@dataclass(frozen=True)
class Step:
    """One protocol step (see the module docstring for the actions)."""

    action: str = param("hold", "", "what the step does", choices=ACTIONS)
    name: str = param("", "", "step name in reports (default: action + index)")
    load: str = param("", "", "gravity load name (gravity / remove_gravity)")
    direction: list[float] = param(None, "-", "gravity direction (in the axes of `frame`)",
                                   default_factory=lambda: [0.0, -1.0, 0.0])
    frame: str = param("model", "", "axes of `direction`: the model frame, or the patient's "
                       "LPS axes of the MRI (gravity does not turn with the chest wall)",
                       choices=FRAMES)
    factor: float = param(1.0, "g", "gravity magnitude in multiples of 9.81 m/s^2", ge=0, le=100)
    plate: str = param("upper", "", "plate to move", choices=PLATES)
    to: str = param("contact", "", "plate target", choices=PLATE_MODES)
    target_D: float | None = param(None, "-", "target compression degree (0..1)", gt=0, lt=0.95)
    target_gap_mm: float | None = param(None, "mm", "target plate gap", gt=0)
    target_force_N: float | None = param(None, "N", "target plate force", gt=0)
    distance_mm: float | None = param(None, "mm", "travel towards the breast (position)")
    force_tol: float = param(0.02, "-", "relative tolerance on a target force", gt=0, lt=0.5)

    def problems(self) -> list[str]:
        out = []
        if self.action in ("gravity", "remove_gravity") and not self.load:
            out.append(f"step '{self.name}': action '{self.action}' needs load = \"<name>\"")
        if self.action == "gravity":
            d = np.asarray(self.direction, float)
            if d.shape != (3,) or not np.linalg.norm(d) > 0:
                out.append(f"step '{self.name}': direction must be 3 numbers, not all zero")
        need = {"degree": "target_D", "gap": "target_gap_mm", "force": "target_force_N",
                "position": "distance_mm"}
        if self.action == "move_plate" and self.to in need and getattr(self, need[self.to]) is None:
            out.append(f"step '{self.name}': to = \"{self.to}\" needs {need[self.to]}")
        return out


@dataclass(frozen=True)
class Protocol:
    """A validated protocol: view, plate geometry and steps."""

    name: str
    view: str
    steps: tuple[Step, ...]
    plates: PlateGeometry = field(default_factory=PlateGeometry)
    angle_deg: float | None = None
    description: str = ""
    source: str = ""

    def to_dict(self) -> dict:
        from regtrack.config import to_table
        return {"name": self.name, "view": self.view, "angle_deg": self.angle_deg,
                "description": self.description, "source": self.source,
                "plates": to_table(self.plates), "steps": [to_table(s) for s in self.steps]}


@dataclass(frozen=True)
class ProtocolOverrides:
    """``[protocol.CC]`` / ``[protocol.MLO]`` of case.toml: change a shipped protocol.

    The targets replace the target of the *last* upper-plate step (exactly one may be
    given); the geometry keys replace those of ``[plates]``.
    """

    target_D: float | None = param(None, "-", "target compression degree (paper: CC 0.38, "
                                   "MLO 0.28)", gt=0, lt=0.95)
    target_gap_mm: float | None = param(None, "mm", "target plate gap instead of D", gt=0)
    target_force_N: float | None = param(None, "N", "target plate force instead of D", gt=0)
    angle_deg: float | None = param(None, "deg", "plate rotation about the AP axis (MLO: 45)",
                                    ge=-90, le=90)
    edge_radius_mm: float | None = param(None, "mm", "plate edge radius", gt=0, le=200)
    posterior_edge_mm: float | None = param(None, "mm", "plate chest-wall edge offset",
                                            ge=-200, le=200)
    window_mm: list[float] | None = param(None, "mm", "[along e_x, across] opening of the grid "
                                          "plate, centred on the lesion")
    protocol: str | None = param(None, "", "protocol file (TOML) replacing the shipped one")

    def problems(self) -> list[str]:
        given = [k for k in ("target_D", "target_gap_mm", "target_force_N")
                 if getattr(self, k) is not None]
        if len(given) > 1:
            return [f"give only one of target_D, target_gap_mm, target_force_N (got {given})"]
        return []


def parse_protocol(table: dict, *, where: str) -> Protocol:
    """Validate a protocol table; raise :class:`ConfigError` naming every bad key."""
    problems: list[str] = []
    known = {"name", "view", "angle_deg", "description", "plates", "steps"}
    for k in table:
        if k not in known:
            problems.append(f"{where}: unknown key '{k}' (valid: {', '.join(sorted(known))})")
    view = str(table.get("view", "")).upper()
    if view not in SIMULATED_VIEWS:
        problems.append(f"{where} view = {table.get('view')!r}: must be one of "
                        + ", ".join(f'"{v}"' for v in SIMULATED_VIEWS))
    plates, p, _ = parse_section(PlateGeometry, table.get("plates"), where=f"{where} [plates]")
    problems += p
    raw = table.get("steps")
    if not isinstance(raw, list) or not raw:
        problems.append(f"{where}: no [[steps]]; a protocol needs at least one step")
        raw = []
    steps = []
    for i, st in enumerate(raw):
        if not isinstance(st, dict):
            problems.append(f"{where} steps[{i}]: must be a table")
            continue
        step, p, w = parse_section(Step, st, where=f"{where} [[steps]] #{i + 1}")
        problems += p + [x.replace("ignored", "not allowed") for x in w]
        if not step.name:
            step = replace(step, name=f"{i + 1}-{step.action}")
        steps.append(step)
    angle = table.get("angle_deg")
    if angle is not None and not isinstance(angle, (int, float)):
        problems.append(f"{where} angle_deg = {angle!r}: expected a number of degrees")
    if problems:
        raise ConfigError("; ".join(problems))
    return Protocol(name=str(table.get("name", view.lower())), view=view, steps=tuple(steps),
                    plates=plates, angle_deg=None if angle is None else float(angle),
                    description=str(table.get("description", "")), source=where)


def load_protocol(path: str | Path) -> Protocol:
    """Read and validate a protocol TOML file."""
    path = Path(path)
    try:
        table = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise ConfigError(f"protocol file {path} not found: give an existing TOML file") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"protocol file {path}: invalid TOML ({err})") from err
    return parse_protocol(table, where=str(path))


def shipped_protocol(name: str) -> Protocol:
    """A shipped protocol by name: ``"cc"``, ``"mlo"`` or ``"biopsy"``."""
    fn = f"{str(name).lower()}.toml"
    res = resources.files("regtrack.mechanics") / "data" / "protocols" / fn
    if not res.is_file():
        avail = sorted(p.name[:-5] for p in (resources.files("regtrack.mechanics") / "data"
                                              / "protocols").iterdir() if p.name.endswith(".toml"))
        raise ConfigError(f"protocol '{name}' unknown: use one of {', '.join(avail)} or a TOML file")
    table = tomllib.loads(res.read_text(encoding="utf-8"))
    return parse_protocol(table, where=f"shipped protocol '{fn}'")


def apply_overrides(protocol: Protocol, ov: ProtocolOverrides) -> Protocol:
    """Protocol with case overrides applied (targets of the last upper-plate step, geometry)."""
    steps = list(protocol.steps)
    target = next((k for k in ("target_D", "target_gap_mm", "target_force_N")
                   if getattr(ov, k) is not None), None)
    if target is not None:
        idx = [i for i, s in enumerate(steps) if s.action == "move_plate" and s.plate == "upper"]
        if not idx:
            raise ConfigError(f"protocol '{protocol.name}': {target} override given but the "
                              "protocol moves no upper plate")
        mode = {"target_D": "degree", "target_gap_mm": "gap", "target_force_N": "force"}[target]
        targets = {"target_D": None, "target_gap_mm": None, "target_force_N": None}
        targets[target] = getattr(ov, target)
        steps[idx[-1]] = replace(steps[idx[-1]], to=mode, **targets)
    geo = protocol.plates
    if ov.edge_radius_mm is not None:
        geo = replace(geo, edge_radius_mm=ov.edge_radius_mm)
    if ov.posterior_edge_mm is not None:
        geo = replace(geo, posterior_edge_mm=ov.posterior_edge_mm)
    if ov.window_mm is not None:
        geo = replace(geo, window_mm=ov.window_mm)
        bad = geo.problems()
        if bad:
            raise ConfigError(f"[protocol.{protocol.view}] " + "; ".join(bad))
    angle = protocol.angle_deg if ov.angle_deg is None else ov.angle_deg
    return replace(protocol, steps=tuple(steps), plates=geo, angle_deg=angle)


def protocol_for_view(view: str, overrides: dict | None = None, *, where: str = "case.toml",
                      base_dir: Path | None = None) -> Protocol:
    """The protocol of ``view`` ("CC"/"MLO"/"BIOPSY"): shipped or from ``protocol = FILE``, plus overrides.

    ``overrides`` is the raw ``[protocol.<VIEW>]`` table; problems raise :class:`ConfigError`.
    """
    v = str(view).upper()
    ov, problems, warnings = parse_section(ProtocolOverrides, overrides,
                                           where=f"{where} [protocol.{v}]")
    if problems or warnings:
        raise ConfigError("; ".join(problems + warnings))
    if ov.protocol:
        p = Path(ov.protocol)
        if base_dir is not None and not p.is_absolute():
            p = base_dir / p
        proto = load_protocol(p)
        if proto.view != v:
            raise ConfigError(f"{where} [protocol.{v}] protocol = {ov.protocol!r} is a "
                              f"{proto.view} protocol; give a {v} protocol")
    else:
        proto = shipped_protocol(v.lower())
    return apply_overrides(proto, ov)
