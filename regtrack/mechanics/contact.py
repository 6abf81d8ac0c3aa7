"""Node-to-rigid-plate contact: the plates' geometry and committed contact state.

Every surface node ``i`` with tributary (reference) area ``A_i`` (mm^2) is a contact
candidate against one rigid plate (:mod:`regtrack.mechanics.plates`: signed gap ``g_i``
in mm, outward normal ``n_i``).  :class:`PlateContact` holds what persists between the
increments of a simulation: the plate and its motion over a step, the augmented-Lagrangian
multipliers ``lambda_i`` (MPa), the node penalties ``eps_i`` (MPa/mm), the pressures of the
last multiplier update ``pbar_i`` (the lagged friction bound) and the friction stick points
``a_i``.  The contact and friction potentials that the step solver minimises, and their
updates, are in :mod:`.potential`; the contact force on a node is

.. math::

    f_i = A_i (p_i n_i + t_i),\\qquad p_i = \\max(0, \\lambda_i - \\varepsilon_i g_i),

with the friction traction ``t_i`` of the lagged C2 friction potential (slip bound ``mu pbar_i``).

Automatic penalty (pressure per mm of penetration, MPa/mm)

.. math::

    \\varepsilon_N = \\kappa E / h

with ``E`` the tissue's small-strain Young modulus (MPa), ``h`` the mean skin edge length
of the contact surface (mm) and ``kappa = penalty_factor``: a penetration of ``h/kappa``
costs a pressure equal to ``E``, so the contact stiffness stays ``kappa`` times the local
stiffness of the surface elements whatever the mesh size or material.  A node whose
violation falls by less than ``slow_uzawa_ratio`` in one multiplier update gets ``eps_i
<- penalty_growth * eps_i`` (at most ``penalty_growth_max * eps_N``); the multipliers
carry the converged pressure, so the growth changes the path of the iteration, not its
limit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from regtrack.config import param
from regtrack.errors import ConfigError
from regtrack.mechanics.plates import RigidPlate
from regtrack.mechanics.potential import friction_terms

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ContactConfig:
    """Contact and friction settings (``[contact]`` of case.toml / simulation config)."""

    friction: float = param(0.1, "-", "Coulomb friction coefficient mu between skin and plates "
                            "(Lapuebla-Ferri et al.: 0.1)", ge=0.0, le=2.0)
    penalty_factor: float = param(20.0, "-", "kappa in eps_N = kappa * E / h (automatic normal "
                                  "penalty)", gt=0.0, le=1e6)
    penalty_mpa_per_mm: float = param(0.0, "MPa/mm", "explicit normal penalty eps_N; 0 = "
                                      "automatic rule", ge=0.0)
    stick_ratio: float = param(0.05, "-", "tangential (stick) penalty eps_T as a fraction of "
                               "eps_N: a node sticks until it has slipped mu p / eps_T (about "
                               "0.1 mm at 1 kPa and the automatic eps_N of a 10k-node breast). "
                               "Ten times stiffer, that transition is narrower than the Newton "
                               "steps of a node on a plate, which then oscillates across it "
                               "(Pelicano exam 26 CC at D = 50 % crawled and cut back)",
                               gt=0.0, le=100.0)
    penetration_tol_mm: float = param(0.02, "mm", "largest accepted penetration at the end of "
                                      "a step (the multipliers are updated until it is met)",
                                      gt=0.0, le=5.0)
    max_penetration_mm: float = param(0.1, "mm", "guard rail: a converged step with a deeper "
                                      "penetration is rejected", gt=0.0)
    friction_tol: float = param(0.001, "-", "accepted error of the lagged friction bound at "
                                "the end of an increment, relative to mu times the plate's "
                                "normal force (or the step's load scale, when larger); a "
                                "frictional end state is determined only to this tolerance "
                                "(docs/physics.md)", gt=0.0, le=0.5)
    first_plate_increment_mm: float = param(2.0, "mm", "protocols: largest plate travel of the "
                                            "first increment of a plate move (the first "
                                            "contact of a plate is the hardest increment)",
                                            gt=0.0)
    max_plate_increment_mm: float = param(
        2.5, "mm", "protocols: largest plate travel per increment of a plate move (0: "
        "1 / [mechanics.solver] initial_increment increments).  Long increments land on another equilibrium of "
        "the compressed breast (friction is integrated per increment); on the phantom CC the "
        "result no longer changes below 2.5 mm", ge=0.0)
    chest_wall_contact: bool = param(True, "", "protocols: no free node may pass behind the "
                                     "chest-wall plane (a frictionless rigid wall at the model's "
                                     "most posterior x: the torso).  Off, with a clamped wall "
                                     "(chest_wall_layer_mm = 0), gives the paper's model, in which "
                                     "the tissue pinched between a plate's rounded edge and the "
                                     "wall is squeezed 5 to 12 mm behind that plane (Pelicano "
                                     "exams 03 and 10): inside the torso")
    chest_wall_layer_mm: float = param(5.0, "mm", "protocols: the chest-wall nodes are held "
                                       "normal to the wall and tangentially by the shear "
                                       "stiffness 2 c1 / h per unit area of a layer of its "
                                       "tissue this thick (the retromammary fat), whose far side "
                                       "is at rest while the breast hangs free and is squeezed "
                                       "with the plates once both hold it "
                                       "(regtrack.mechanics.support).  0 clamps them (the "
                                       "paper's model), which the plates cannot compress: the "
                                       "base is taller than the final gap", ge=0.0, le=100.0)
    behind_wall_warn_mm: float = param(10.0, "mm", "reports: warn (log and the step's "
                                       "'warnings') when a node ends a protocol step deeper "
                                       "than this behind the chest-wall plane (the torso is "
                                       "there; see chest_wall_contact); every step reports the "
                                       "depth as behind_chest_wall_mm", gt=0.0)
    self_contact_gap_mm: float = param(0.5, "mm", "self-contact of the outer surface: a node "
                                       "and a triangle outside its 2-ring repel by a log barrier "
                                       "(regtrack.mechanics.selfcontact) once closer than this, "
                                       "so folded skin rests on the skin below it instead of "
                                       "entering the tissue.  Where the reference surface "
                                       "already comes closer to itself, the reach is half that "
                                       "distance (logged).  0: no self-contact, the skin may "
                                       "pass through itself (measured as skin_overlap_mm)",
                                       ge=0.0, le=5.0)
    skin_overlap_warn_mm: float = param(1.0, "mm", "reports: warn (log and the step's "
                                        "'warnings') when a skin node ends a protocol step "
                                        "deeper than this inside the tissue: the skin folded "
                                        "through itself where the self-contact barrier cannot "
                                        "stop it (a crease sharper than the mesh, or the barrier "
                                        "off); every step reports the depth as "
                                        "skin_overlap_mm (regtrack.mechanics.overlap)", gt=0.0)
    edge_band_mm: float = param(10.0, "mm", "reports: the plate force carried by the skin "
                                "that lay (reference configuration) within this distance in "
                                "front of the plate's chest-wall edge, or behind it, is "
                                "reported apart as edge_normal_force_N: the tissue attached "
                                "near the chest wall", ge=0.0)
    penalty_growth: float = param(4.0, "-", "a node whose violation "
                                  "fell by less than slow_uzawa_ratio in one multiplier update "
                                  "gets its penalty multiplied by this (1: never)", ge=1.0, le=100.0)
    slow_uzawa_ratio: float = param(0.3, "-", "violation ratio between two multiplier updates "
                                    "above which a node's penalty grows", gt=0.0, lt=1.0)
    penalty_growth_max: float = param(256.0, "-", "largest node penalty as a multiple of the "
                                      "automatic one", ge=1.0, le=1e6)


def tributary_areas(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Nodal tributary area (mm^2): a third of the area of every adjacent triangle.

    Parameters
    ----------
    points : (N, 3) float
        Node coordinates (mm).
    tris : (S, 3) int
        Surface triangles.

    Returns
    -------
    (N,) float
        ``A_i = sum_{T ∋ i} |T| / 3``; zero for nodes off the surface.
    """
    p = np.asarray(points, float)[np.asarray(tris)]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return np.bincount(np.asarray(tris).ravel(), np.repeat(area / 3.0, 3), minlength=len(points))


def mean_edge_length(points: np.ndarray, tris: np.ndarray) -> float:
    """Mean edge length (mm) of a triangle surface (edges counted once per triangle)."""
    p = np.asarray(points, float)[np.asarray(tris)]
    e = np.concatenate([p[:, 1] - p[:, 0], p[:, 2] - p[:, 1], p[:, 0] - p[:, 2]])
    return float(np.linalg.norm(e, axis=1).mean())


def automatic_penalty(config: ContactConfig, *, young_mpa: float, h_mm: float) -> float:
    """Normal penalty ``eps_N`` (MPa/mm): explicit value, or ``kappa * E / h``."""
    if config.penalty_mpa_per_mm > 0:
        return float(config.penalty_mpa_per_mm)
    if not (young_mpa > 0 and h_mm > 0):
        raise ConfigError(f"contact: automatic penalty needs E > 0 and h > 0 (got E={young_mpa} "
                          f"MPa, h={h_mm} mm); set [contact] penalty_mpa_per_mm")
    return float(config.penalty_factor * young_mpa / h_mm)


class PlateContact:
    """Frictional contact of a set of body nodes against one moving rigid plate.

    Parameters
    ----------
    plate : RigidPlate
        The plate at the start of the simulation.
    reference : (N, 3) float
        Reference coordinates of all model nodes (mm).
    nodes : (M,) int
        Candidate contact nodes (skin nodes).
    areas : (M,) float
        Tributary skin area of each candidate node (mm^2).
    config : ContactConfig
    penalty : float
        Normal penalty ``eps_N`` (MPa/mm), see :func:`automatic_penalty`.
    name : str, optional
        Name in reports (default: the plate's name).
    """

    def __init__(self, plate: RigidPlate, reference: np.ndarray, nodes, areas, *,
                 config: ContactConfig, penalty: float, name: str | None = None):
        self.name = name or plate.name
        self.plate = plate
        self.X = np.asarray(reference, float)
        self.nodes = np.asarray(nodes, np.int64)
        self.areas = np.asarray(areas, float)
        if self.areas.shape != self.nodes.shape or np.any(self.areas < 0):
            raise ConfigError(f"contact '{self.name}': areas must be >= 0, one per node")
        self.config = config
        self.eps_n = float(penalty)
        self.eps_t = float(penalty * config.stick_ratio)
        self.mu = float(config.friction)
        m = len(self.nodes)
        # committed state (end of the last converged increment)
        self.eps_node = np.full(m, self.eps_n)  # node-wise normal penalty (grows, see .potential)
        self._lam = np.zeros(m)  # multipliers (MPa)
        self._pconv = np.zeros(m)  # pressures of the last multiplier update: the friction bound / mu
        self._anchor = self.plate.to_local(self.X[self.nodes])  # stick points, plate-local
        self._plate0 = plate
        self.n_slip = 0  # nodes that slid in the last committed increment
        self.motion: tuple[np.ndarray, np.ndarray] | None = None

    # -- committed state -------------------------------------------------------------
    def get_state(self) -> dict:
        """Copy of the committed state (plate, stick points, multipliers, pressures, node
        penalties, motion)."""
        return {"plate": self.plate, "anchor": self._anchor.copy(), "lam": self._lam.copy(),
                "pconv": self._pconv.copy(), "motion": self.motion, "eps": self.eps_node.copy()}

    def set_state(self, state: dict) -> None:
        """Restore (or commit) a state of the form :meth:`get_state` returns."""
        self.plate = self._plate0 = state["plate"]
        self._anchor = state["anchor"].copy()
        self._lam = state["lam"].copy()
        self._pconv = state["pconv"].copy()
        if "eps" in state:
            self.eps_node = state["eps"].copy()
        self.motion = state["motion"]

    def min_gap(self, u: np.ndarray) -> float:
        """Smallest signed gap (mm) of the candidate nodes at displacement ``u`` (N, 3)."""
        x = self.X[self.nodes] + np.asarray(u, float).reshape(-1, 3)[self.nodes]
        return float(self.plate.query(x).gap.min())

    # -- plate motion -----------------------------------------------------------------
    def place(self, plate: RigidPlate) -> None:
        """Put the plate at rest at ``plate``: the start of the next step, no motion."""
        self.plate = self._plate0 = plate
        self.motion = None

    def set_motion(self, start, end) -> None:
        """Move the plate face origin linearly from ``start`` to ``end`` (mm) over t in [0, 1]."""
        self.motion = (np.asarray(start, float).reshape(3), np.asarray(end, float).reshape(3))

    def begin_step(self, step: Any) -> None:
        """Start of a protocol step: the committed plate position is the step's start."""
        self._plate0 = self.plate

    def set_time(self, t: float) -> None:
        """Move the plate to its position at pseudo-time ``t`` of the step's motion."""
        if self.motion is not None:
            a, b = self.motion
            self.plate = self.plate.moved_to(a + float(t) * (b - a))

    # -- forces and reports -----------------------------------------------------------
    def nodal_forces(self, u: np.ndarray) -> tuple[np.ndarray, dict]:
        """Contact force on each candidate node (M, 3) in N at ``u`` (N, 3) mm with the
        committed multipliers, node penalties, stick points and friction bound, and state
        figures (active mask, gap mm, pressure MPa, penetration mm)."""
        x = self.X[self.nodes] + np.asarray(u, float).reshape(-1, 3)[self.nodes]
        q = self.plate.query(x)
        p = np.maximum(self._lam - self.eps_node * q.gap, 0.0)
        act = p > 0
        f = (self.areas * p)[:, None] * q.normal
        if self.mu > 0:
            anchor = self.plate.to_model(self._anchor)
            bound = np.where(act, self.mu * self._pconv, 0.0)
            f = f - friction_terms(x, anchor, q.normal, bound, self.eps_t, self.areas)[1]
        pen = float(max(0.0, -q.gap[act].min())) if act.any() else 0.0
        return f, {"active": act, "gap": q.gap, "pressure": p, "max_penetration_mm": pen}

    def report(self, u: np.ndarray) -> dict:
        """Plate force (N), maximum penetration (mm), active nodes, contact area (mm^2).

        ``edge_normal_force_N`` is the part of ``normal_force_N`` carried by the skin that,
        in the reference configuration, lies behind the plate's chest-wall edge or within
        ``edge_band_mm`` in front of it (plate-local ``s`` of the reference position below
        the edge's ``s`` plus the band): the tissue attached near the fixed chest wall,
        wherever the compression has moved it.  ``n_slip`` counts the nodes that slid in
        the increment last committed.
        """
        f, st = self.nodal_forces(u)
        force_on_plate = -f.sum(axis=0)
        n0 = self.plate.normal
        fn = float(-(force_on_plate @ n0))
        ft = force_on_plate - (force_on_plate @ n0) * n0
        act = st["active"]
        s_ref = self.plate.to_local(self.X[self.nodes])[:, 0]  # reference positions
        edge = act & (s_ref < self.plate.s_range[0] + self.config.edge_band_mm)
        fn_edge = float(f[edge].sum(axis=0) @ n0)
        return {"name": self.name,
                "force_N": force_on_plate.tolist(),
                "normal_force_N": fn,
                "tangential_force_N": float(np.linalg.norm(ft)),
                "edge_normal_force_N": fn_edge,
                "edge_band_mm": self.config.edge_band_mm,
                "max_penetration_mm": st["max_penetration_mm"],
                "n_active": int(act.sum()),
                "n_slip": self.n_slip,
                "contact_area_mm2": float(self.areas[act].sum()),
                "plate_origin_mm": self.plate.origin.tolist()}
