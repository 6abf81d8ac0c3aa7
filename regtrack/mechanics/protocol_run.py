"""The protocol engine: runs a :class:`~regtrack.mechanics.protocol.Protocol` step by step.

The engine owns the protocol state (displacement, active gravity loads, the two plates
with their frictional contact) and calls a *step solver* for each mechanical step::

    solve(u0, g_start, g_end, contributions, step_name) -> (u, stats: dict)

which must return an equilibrium ``u`` (N, 3) mm after ramping the gravity vector
(m/s^2, model frame) from ``g_start`` to ``g_end`` while each contribution's
``set_time(t)`` moves its plate (pseudo-time t: 0 -> 1).
:func:`regtrack.mechanics.minimise.minimiser_from_problem` adapts the mechanics core's
``minimise_step``; tests use small mock solvers.

Plate placement and the chest wall: :mod:`.placement`.  The plates take part from the
protocol's first plate step on: until then the breast hangs free (the prone gravity
unloaded with no plate near it), and that step places both plates ``clearance_mm`` from
the shape the body has then.  So the unloaded reference state is the same for every view,
whichever way its plates will face.  The force carried by the surface
near the wall is reported apart (``edge_band_mm``; ``upper_body_force_N`` in
:func:`regtrack.mechanics.run_view.summarise`).

Targets of an upper-plate move: the plate is first brought to touch the breast (no
force), which measures the uncompressed thickness ``T_0`` (plate gap at that touch).  From
then on both plates hold the breast and the body beyond the chest wall is squeezed with
them (:mod:`.support`: each chest-wall node's layer anchored to the plates' displacement
interpolated by its height between them at the touch).  The plate then travels to the gap
``(1 - D) T_0`` (degree), the given gap (gap), or until the plate force reaches the target
within ``force_tol`` (force: marching + secant, each trial solved from the last accepted
state).  After every step the penetration guard rail rejects a state with a node deeper
than ``max_penetration_mm`` in a plate.

Force balance: every step reports ``solver.force_balance`` (:func:`.problem.force_balance`), the
resultant of the residual over the free nodes (the sum of chest-wall reaction, plate
forces and weight) against the largest of those loads; the step solver refuses a state
whose imbalance exceeds ``[mechanics.solver] stall_force_tol``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from regtrack.errors import ConfigError, ResultCheckError, SolverDidNotConvergeError
from regtrack.mechanics import compression as comp
from regtrack.mechanics.contact import ContactConfig, PlateContact
from regtrack.mechanics.linsolve import serial_openblas
from regtrack.mechanics.overlap import overlaps
from regtrack.mechanics.placement import BodySetup, behind_chest_wall, chest_wall, make_plates
from regtrack.mechanics.protocol import G_STANDARD, Protocol, Step
from regtrack.mechanics.support import squeeze_weights

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepControl:
    """How the protocol engine asks a step to be incremented.

    single : one increment first (a touching plate; the solver cuts it back if it fails).
    max_increment : the largest pseudo-time increment (a plate move's travel cap / its
        distance), or None for the solver's own gravity increments.
    T0_mm : the uncompressed thickness, for the progress's ``D = 1 - gap / T0``.
    body_motion : ``body_motion(t) -> (N, 3)`` mm, the displacement at pseudo-time ``t``
        of the body beyond the chest-wall layer at each node, squeezed with the plates once
        both hold the breast (:meth:`.support.WallSupport.moved`); None while the breast
        hangs free (the body at rest).
    """

    single: bool = False
    max_increment: float | None = None
    T0_mm: float | None = None
    body_motion: Callable[[float], np.ndarray] | None = None


#: ``solve(u0, g0, g1, contacts, step_name, control) -> (u, stats)``: one protocol step
#: from gravity ``g0`` to ``g1`` (m/s^2) with the contacts' plates moving over it.
StepSolver = Callable[[np.ndarray, np.ndarray, np.ndarray, list, str, StepControl],
                      tuple[np.ndarray, dict]]


def gravity_direction(step: Step, axes: np.ndarray | None) -> np.ndarray:
    """A gravity step's direction in the model frame: as given, or turned from the
    patient's LPS axes by the model frame's ``axes`` (rows: model axes in LPS; None: the
    patient-aligned frame, x anterior, y superior)."""
    from regtrack.model.types import AnatomicalFrame

    d = np.asarray(step.direction, float)
    if step.frame == "patient":
        d = (AnatomicalFrame.standard("L").axes if axes is None else np.asarray(axes, float)) @ d
    return d


@dataclass
class StepRecord:
    """State and figures at the end of one protocol step."""

    name: str
    action: str
    u: np.ndarray
    gravity_ms2: np.ndarray
    plates: dict
    contact: dict
    gap_mm: float | None  # None before the plates are placed
    T0_mm: float | None = None
    D: float | None = None
    D_mean: float | None = None
    max_penetration_mm: float = 0.0
    solver: dict = field(default_factory=dict)
    behind_chest_wall_mm: float | None = None
    behind_chest_wall_nodes: int | None = None
    skin_overlap_mm: float | None = None
    skin_overlap_nodes: int | None = None
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready figures (no displacement)."""
        return {"name": self.name, "action": self.action, "gravity_ms2": self.gravity_ms2.tolist(),
                "plates": self.plates, "contact": self.contact, "plate_gap_mm": self.gap_mm,
                "T0_mm": self.T0_mm, "D": self.D, "D_mean": self.D_mean,
                "max_penetration_mm": self.max_penetration_mm,
                "behind_chest_wall_mm": self.behind_chest_wall_mm,
                "behind_chest_wall_nodes": self.behind_chest_wall_nodes,
                "skin_overlap_mm": self.skin_overlap_mm,
                "skin_overlap_nodes": self.skin_overlap_nodes,
                "warnings": self.warnings, "solver": self.solver}


@dataclass
class ProtocolResult:
    """Records of the converged steps; ``error`` says where a run stopped."""

    protocol: Protocol
    steps: list[StepRecord]
    plate_frame: dict
    error: str | None = None
    materials: dict = field(default_factory=dict)  # tissue stiffness summary (tissue_model)
    self_contact_reach_mm: float | None = None  # the skin barrier's reach (None: off)

    @property
    def complete(self) -> bool:
        return self.error is None and len(self.steps) == len(self.protocol.steps)

    @property
    def u(self) -> np.ndarray:
        return self.steps[-1].u


def _merge_stats(a: dict, b: dict) -> dict:
    """Solver statistics of two solves of one step: counts and times added, the rest of ``b``."""
    if not a:
        return dict(b)
    out = dict(b)
    for k, v in a.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool) and isinstance(b.get(k), (int, float)):
            out[k] = v + b[k]
    return out


def _gap(plates: dict[str, PlateContact], n: np.ndarray) -> float:
    return float((plates["upper"].plate.origin - plates["lower"].plate.origin) @ n)


def _touch(pc: PlateContact, u: np.ndarray) -> None:
    """Translate a plate along its normal until it just touches the body (no force)."""
    pc.place(pc.plate.translated(pc.min_gap(u) * pc.plate.normal))


class ProtocolRunner:
    """Run a protocol on a body with a step solver (see the module docstring)."""

    def __init__(self, body: BodySetup, protocol: Protocol, solve: StepSolver, *,
                 config: ContactConfig | None = None):
        self.body = body
        self.protocol = protocol
        self.solve = solve
        self.config = config or ContactConfig()
        # placed around the reference shape here (a bad geometry is refused before any
        # solve) and again around the current shape at the first plate step
        self.plates, self.frame = make_plates(body, protocol, config=self.config)
        self.plates_in = False
        self.wall = chest_wall(body, self.config)
        self.n = self.frame.normal
        self.u = np.zeros_like(body.points)
        self.g = np.zeros(3)
        self.loads: dict[str, np.ndarray] = {}
        self.records: list[StepRecord] = []
        self._tmean0: float | None = None
        # once both plates hold the breast (the upper one has touched it): each node's
        # place between them (0 lower, 1 upper) and the plates' origins then (mm)
        self._squeeze: tuple[np.ndarray, dict[str, np.ndarray]] | None = None

    @property
    def contacts(self) -> dict[str, PlateContact]:
        """Every contact taking part: the chest wall (not a plate: never moved or drawn)
        and, from the first plate step on, the plates."""
        out = dict(self.plates) if self.plates_in else {}
        return out | ({self.wall.name: self.wall} if self.wall is not None else {})

    def _bring_plates(self) -> None:
        """Place the plates ``clearance_mm`` from the body's current shape (first plate step)."""
        if not self.plates_in:
            self.plates, _ = make_plates(self.body, self.protocol, config=self.config, u=self.u)
            self.plates_in = True

    # -- one solve ------------------------------------------------------------------
    def _body_motion(self) -> Callable[[float], np.ndarray] | None:
        """The body's displacement beyond the chest-wall layer over the coming solve: each
        node moved with the plates in proportion to its place between them at the upper
        plate's first touch (None before it)."""
        if self._squeeze is None:
            return None
        w, touch = self._squeeze

        def shift(name: str, t: float) -> np.ndarray:
            pc = self.plates[name]
            a, b = pc.motion if pc.motion is not None else (pc.plate.origin, pc.plate.origin)
            return a + t * (b - a) - touch[name]

        def motion(t: float) -> np.ndarray:
            return np.outer(1.0 - w, shift("lower", t)) + np.outer(w, shift("upper", t))
        return motion

    def _solve(self, g_end: np.ndarray, name: str, *, single: bool = False,
               max_increment: float | None = None, T0_mm: float | None = None) -> dict:
        contribs = list(self.contacts.values())
        for c in contribs:
            c.begin_step(name)
        control = StepControl(single=single, T0_mm=T0_mm, max_increment=(
            max_increment if max_increment is not None and max_increment < 1.0 else None),
            body_motion=self._body_motion())
        u, stats = self.solve(self.u, self.g, g_end, contribs, name, control)
        self.u = np.asarray(u, float).reshape(-1, 3)
        self.g = np.asarray(g_end, float)
        for c in contribs:
            c.set_time(1.0)
            c.place(c.plate)
        return dict(stats or {})

    def _penetration(self) -> tuple[float, dict]:
        reps = {k: c.report(self.u) for k, c in self.contacts.items()}
        return max((r["max_penetration_mm"] for r in reps.values()), default=0.0), reps

    def _move(self, pc: PlateContact, distance: float, name: str, T0_mm: float | None = None
              ) -> dict:
        """Move a plate along its normal by ``distance`` (mm).

        A move longer than ``first_plate_increment_mm`` is solved in two parts: that first
        travel on its own (where contact spreads from a few nodes to many, the hardest
        increment of the move), then the rest with the solver's own load stepping, in
        increments of at most ``max_plate_increment_mm`` of travel (2.5 mm by default: longer
        increments land on another equilibrium, see that option).
        """
        first = self.config.first_plate_increment_mm
        parts = [distance] if abs(distance) <= 1.5 * first else [np.sign(distance) * first,
                                                                 distance - np.sign(distance) * first]
        stats: dict = {}
        cap = self.config.max_plate_increment_mm
        for k, d in enumerate(parts):
            start = pc.plate.origin.copy()
            pc.set_motion(start, start + d * pc.plate.normal)
            stats = _merge_stats(stats, self._solve(self.g, name, single=len(parts) > 1 and k == 0,
                                                    max_increment=cap / abs(d) if cap > 0 else None,
                                                    T0_mm=T0_mm))
        return stats

    def _snapshot(self):
        return (self.u.copy(), {k: c.get_state() for k, c in self.contacts.items()})

    def _restore(self, snap) -> None:
        self.u = snap[0].copy()
        for k, c in self.contacts.items():
            c.set_state(snap[1][k])

    def _force_target(self, pc: PlateContact, step: Step, t0: float) -> dict:
        """March the plate until its normal force reaches the target, then refine (secant)."""
        target = float(step.target_force_N)
        stats: dict = {"trials": 0}
        d_done, f_done = 0.0, 0.0
        chunk = 0.05 * t0
        for _ in range(60):
            snap = self._snapshot()
            self._move(pc, chunk, step.name)
            stats["trials"] += 1
            f = pc.report(self.u)["normal_force_N"]
            if abs(f - target) <= step.force_tol * target:
                return stats
            if f < target:
                # accept and extrapolate (secant on the force-travel curve, growth <= 2x)
                slope = (f - f_done) / chunk if f > f_done else 0.0
                d_done, f_done = d_done + chunk, f
                if d_done >= 0.9 * t0:
                    raise ResultCheckError(f"step '{step.name}': the plate force {f:.3g} N stays "
                                           f"below target_force_N = {target} N at 90 % compression; "
                                           "lower the target")
                want = (target - f) / slope if slope > 0 else chunk
                chunk = float(np.clip(want, 0.2 * chunk, 2.0 * chunk))
                continue
            # overshoot: go back and take a secant-sized shorter move
            self._restore(snap)
            frac = (target - f_done) / (f - f_done) if f > f_done else 0.5
            chunk = chunk * float(np.clip(frac, 0.1, 0.9))
        raise ResultCheckError(f"step '{step.name}': target force {target} N not reached in 60 "
                               "trials; give target_gap_mm or target_D instead")

    # -- steps --------------------------------------------------------------------------
    def _run_step(self, step: Step) -> StepRecord:
        T0 = None
        stats: dict = {}
        if step.action == "gravity":
            d = gravity_direction(step, self.body.axes)
            vec = step.factor * G_STANDARD * d / np.linalg.norm(d)
            self.loads[step.load] = self.loads.get(step.load, np.zeros(3)) + vec
            stats = self._solve(sum(self.loads.values(), np.zeros(3)), step.name)
        elif step.action == "remove_gravity":
            if step.load not in self.loads:
                raise ConfigError(f"step '{step.name}': gravity load '{step.load}' is not active "
                                  f"(active: {', '.join(self.loads) or 'none'})")
            self.loads.pop(step.load)
            stats = self._solve(sum(self.loads.values(), np.zeros(3)), step.name)
        elif step.action == "hold":
            stats = self._solve(self.g, step.name)
        else:
            self._bring_plates()
            pc = self.plates[step.plate]
            if step.to == "position":
                stats = self._move(pc, float(step.distance_mm), step.name)
            else:
                _touch(pc, self.u)
                if step.plate == "upper" and self._squeeze is None:
                    # both plates hold the breast from here on, and the body beyond the
                    # chest wall is squeezed with them
                    low = self.plates["lower"].plate
                    w = squeeze_weights(self.body.points + self.u, low.origin, self.n,
                                        _gap(self.plates, self.n))
                    self._squeeze = (w, {k: c.plate.origin.copy() for k, c in self.plates.items()})
                if step.to != "contact":
                    if step.plate != "upper":
                        raise ConfigError(f"step '{step.name}': to = '{step.to}' moves the upper "
                                          "plate only; use to = 'contact' or 'position' for the lower")
                    T0 = _gap(self.plates, self.n)
                    self._tmean0 = self._mean_thickness()
                    if step.to == "force":
                        stats = _merge_stats(stats, self._force_target(pc, step, T0))
                    else:
                        gap = (comp.gap_for_degree(T0, step.target_D) if step.to == "degree"
                               else float(step.target_gap_mm))
                        if not 0 < gap < T0:
                            raise ConfigError(f"step '{step.name}': target gap {gap:.2f} mm must "
                                              f"be below the uncompressed thickness {T0:.2f} mm")
                        stats = _merge_stats(stats, self._move(pc, T0 - gap, step.name,
                                                               T0_mm=T0))
        pen, reps = self._penetration()
        if pen > self.config.max_penetration_mm:
            raise ResultCheckError(
                f"step '{step.name}': a surface node is {pen:.3f} mm inside a plate (limit "
                f"{self.config.max_penetration_mm} mm); lower [contact] penetration_tol_mm "
                "or raise penalty_factor")
        gap = _gap(self.plates, self.n) if self.plates_in else None
        rec = StepRecord(name=step.name, action=step.action, u=self.u.copy(), gravity_ms2=self.g.copy(),
                         plates=({k: c.plate.to_dict() for k, c in self.plates.items()}
                                 if self.plates_in else {}),
                         contact=reps, gap_mm=gap, max_penetration_mm=pen, solver=stats)
        depth, count = behind_chest_wall(self.body.points, self.u, self.body.fixed)
        rec.behind_chest_wall_mm, rec.behind_chest_wall_nodes = depth, count
        if depth is not None and depth > self.config.behind_wall_warn_mm:
            msg = (f"step '{step.name}': {count} nodes end more than 1 mm behind the chest-wall "
                   f"plane, the deepest {depth:.1f} mm (over [contact] behind_wall_warn_mm = "
                   f"{self.config.behind_wall_warn_mm:g}): tissue inside the torso; its plate "
                   "force and shape near the wall are not physical (see [contact] "
                   "chest_wall_contact)")
            log.warning(msg)
            rec.warnings.append(msg)
        over = overlaps(self.body.points, self.body.tets, self.body.surface, self.u)
        rec.skin_overlap_mm, rec.skin_overlap_nodes = over.depth, len(over.nodes)
        if over.depth > self.config.skin_overlap_warn_mm:
            k = int(over.nodes[np.argmax(over.d)])
            x = self.body.points[k] + self.u[k]
            why = ("a crease sharper than the mesh, which the self-contact barrier cannot hold"
                   if self.config.self_contact_gap_mm > 0 else
                   "self-contact is off: [contact] self_contact_gap_mm = 0")
            msg = (f"step '{step.name}': {len(over.nodes)} skin nodes end inside the tissue, the "
                   f"deepest {over.depth:.1f} mm at ({x[0]:.0f}, {x[1]:.0f}, {x[2]:.0f}) mm, "
                   f"{x[0] - self.body.points[:, 0].min():.0f} mm in front of the chest-wall "
                   f"plane (over [contact] skin_overlap_warn_mm = "
                   f"{self.config.skin_overlap_warn_mm:g}): the skin folded through itself "
                   f"there ({why}), so its shape and stresses there are not physical")
            log.warning(msg)
            rec.warnings.append(msg)
        if T0 is not None:
            rec.T0_mm = T0
            rec.D = comp.compression_degree(T0, gap)
            if self._tmean0:
                rec.D_mean = 1.0 - self._mean_thickness() / self._tmean0
        return rec

    def _mean_thickness(self) -> float:
        b = self.body
        x = b.points + self.u
        edge = self.plates["lower"].plate.s_range[0]
        tmask = b.points[b.tets].mean(axis=1)[:, 0] >= edge
        smask = b.points[b.surface].mean(axis=1)[:, 0] >= edge
        return comp.mean_thickness(x, b.tets, b.surface, self.n, tet_mask=tmask,
                                   surface_mask=smask)

    @serial_openblas()
    def run(self) -> ProtocolResult:
        """Run every step; on failure raise with the partial result in ``last_converged``.
        OpenBLAS runs on one thread meanwhile, so that the result does not depend on the
        core count (:func:`regtrack.mechanics.linsolve.serial_openblas`)."""
        result = ProtocolResult(self.protocol, self.records, self.frame.to_dict())
        for i, step in enumerate(self.protocol.steps):
            log.info("protocol %s: step %d/%d '%s'", self.protocol.name, i + 1,
                     len(self.protocol.steps), step.name)
            try:
                self.records.append(self._run_step(step))
            except SolverDidNotConvergeError as err:
                result.error = f"step '{step.name}' did not converge: {err}"
                raise type(err)(f"protocol '{self.protocol.name}' step {i + 1} '{step.name}': "
                                f"{err}", load_fraction=err.load_fraction,
                                last_converged=result) from err
            except ResultCheckError as err:
                result.error = str(err)
                err.last_converged = result  # type: ignore[attr-defined]
                raise
            rec = self.records[-1]
            forces = ", ".join(f"{k} {round(v['normal_force_N'], 2) + 0.0:.2f} N"
                               for k, v in rec.contact.items())
            log.info("  gap %s mm, D %s, penetration %.4f mm; forces: %s",
                     "-" if rec.gap_mm is None else f"{rec.gap_mm:.2f}",
                     "-" if rec.D is None else f"{100 * rec.D:.1f} %", rec.max_penetration_mm,
                     forces or "no contact")
        return result
