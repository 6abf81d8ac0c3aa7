"""Frictional node-to-rigid-plate contact: a solver :class:`Contribution`.

Every skin node ``i`` with tributary (reference) skin area ``A_i`` (mm^2) carries a
contact pressure ``p_i`` (MPa) and a tangential traction ``t_i`` (MPa) against one rigid
plate (:mod:`regtrack.mechanics.plates`).  With the signed gap ``g_i`` (mm) and the outward
plate normal ``n_i``:

Normal contact (augmented Lagrangian, or pure penalty with ``lambda = 0``)

.. math::

    p_i = \\max(0,\\; \\lambda_i - \\varepsilon_N\\, g_i)

with the multipliers updated after each converged solve (Uzawa): ``lambda_i <- p_i``
until the largest penetration is below ``penetration_tol_mm``.  The penetration is then
bounded by the tolerance whatever the tissue stiffness; plain penalty leaves ``|g| ~ p /
eps_N``.

Automatic penalty (pressure per mm of penetration, MPa/mm)

.. math::

    \\varepsilon_N = \\kappa\\, E / h

with ``E`` the tissue's small-strain Young modulus (MPa), ``h`` the mean skin edge length
of the contact surface (mm) and ``kappa = penalty_factor``: a penetration of ``h/kappa``
costs a pressure equal to ``E``, so the contact stiffness stays ``kappa`` times the local
stiffness of the surface elements whatever the mesh size or material.

Node-wise penalty growth: Uzawa reduces a node's violation by about ``k_i / (k_i + eps_N
A_i)`` per update (``k_i`` the stiffness of the body under the node), which is slow where
skin is pressed by the rounded plate edge next to the fixed chest wall.  A node whose
violation fell by less than ``slow_uzawa_ratio`` in one update gets ``eps_i <-
penalty_growth * eps_i`` (at most ``penalty_growth_max * eps_N``); the multipliers carry the
converged pressure, so the growth changes the path of the iteration, not its limit.  A node
whose multiplier only grows at the cap (skin pinned between a plate edge and the chest
wall) stalls the updates; after ``stalled_uzawa_updates`` such updates the increment is
cut back (:meth:`PlateContact._check_stall`).

Regularised Coulomb friction (stick/slip return mapping, :mod:`.friction`): with the
stick point ``a_i`` (plate-local, committed at the end of each converged increment) and
``g_T = (I - n n^T)(x_i - a_i)``, ``t = -eps_T g_T`` while ``eps_T |g_T| <= B`` (stick),
else ``t = -B g_T / |g_T|`` (slip; the stick point is then dragged so that
``|g_T| = B / eps_T``), with the slip bound ``B = mu p``: of the current iterate
(``friction_bound = "current"``, consistent non-symmetric tangent, the default) or of the
last converged solve (``"multiplier"``, Simo & Laursen 1992, re-solved until the friction
forces agree within ``friction_tol``).  ``stick_slip_freeze``, ``slip_predictor`` and
``predictor`` are opt-in variants of the residual Newton solver.

The nodal force on the body is ``f_i = A_i (p_i n_i + t_i)``; the residual added to the
solver's ``R = f_int - f_ext`` is ``-f_i`` and the tangent is its derivative for the
current bound and state.

*Edge curvature term.*  On a rounded edge of radius ``R`` the normal turns as a node
slides, and the exact tangent of the normal force has the term ``-A p dn/dx`` (``dn/dx =
(I - n n^T)/(R + g)``), a negative tangential stiffness ``-A p / (R + g)``.  Where skin is
pinched between the edge and the fixed chest wall it exceeds the tissue's tangential
stiffness and the tangent turns indefinite.  By default (``curvature_tangent = false``)
the term is left out of the tangent: the residual stays exact, so a converged state is the
same equilibrium, and convergence on edge nodes is linear instead of quadratic.  The
residual Newton solver retries a failed increment with the other tangent
(``swap_tangent``, counted in ``tangent_retries``).  Measured figures:
docs/performance-mechanics.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from regtrack.config import param
from regtrack.errors import ConfigError
from regtrack.mechanics import friction as fr
from regtrack.mechanics.plates import RigidPlate

log = logging.getLogger(__name__)

METHODS = ("augmented-lagrangian", "penalty")
BOUNDS = ("multiplier", "current")


@dataclass(frozen=True)
class ContactConfig:
    """Contact and friction settings (``[contact]`` of case.toml / simulation config)."""

    friction: float = param(0.1, "-", "Coulomb friction coefficient mu between skin and plates "
                            "(Lapuebla-Ferri et al.: 0.1)", ge=0.0, le=2.0)
    method: str = param("augmented-lagrangian", "", "normal contact enforcement",
                        choices=METHODS)
    penalty_factor: float = param(20.0, "-", "kappa in eps_N = kappa * E / h (automatic normal "
                                  "penalty)", gt=0.0, le=1e6)
    penalty_mpa_per_mm: float = param(0.0, "MPa/mm", "explicit normal penalty eps_N; 0 = "
                                      "automatic rule", ge=0.0)
    stick_ratio: float = param(0.5, "-", "tangential (stick) penalty eps_T as a fraction of "
                               "eps_N", gt=0.0, le=100.0)
    penetration_tol_mm: float = param(0.02, "mm", "augmented Lagrangian: largest accepted "
                                      "penetration", gt=0.0, le=5.0)
    max_penetration_mm: float = param(0.1, "mm", "guard rail: a converged step with a deeper "
                                      "penetration is rejected", gt=0.0)
    friction_bound: str = param("current", "", "slip bound mu*p from the last converged "
                                "solve, fixed during Newton ('multiplier'), or from the current "
                                "iterate ('current')", choices=BOUNDS)
    friction_tol: float = param(0.005, "-", "accepted error of the friction forces (lagged "
                                "bound, frozen state) relative to mu * normal force", gt=0.0,
                                le=0.5)
    friction_tol_cycling: float = param(0.05, "-", "friction_tol after two friction re-solves "
                                        "of one increment (nodes on the stick/slip boundary "
                                        "that flip state at every re-solve); 5 % of mu N is "
                                        "0.5 % of the plate force at mu = 0.1", gt=0.0, le=0.5)
    stick_slip_freeze: int = param(0, "-", "Newton iterations of a solve after which the "
                                   "stick/slip state is frozen (0: never)", ge=0, le=1000)
    hold_state_in_line_search: bool = param(False, "", "line-search evaluations use the "
                                            "stick/slip state of the Newton iterate")
    slip_predictor: bool = param(False, "", "first Newton iterate of an increment: nodes that "
                                 "slipped in the previous increment are taken as slipping")
    first_plate_increment_mm: float = param(2.0, "mm", "protocols: largest plate travel of the "
                                            "first increment of a plate move (the first "
                                            "contact of a plate is the hardest increment)",
                                            gt=0.0)
    max_plate_increment_mm: float = param(
        2.5, "mm", "protocols: largest plate travel per increment of a plate move (0: the "
        "solver's own max_increment only).  Long increments land on another equilibrium of "
        "the compressed breast (friction is integrated per increment); on the phantom CC the "
        "result no longer changes below 2.5 mm", ge=0.0)
    predictor: bool = param(False, "", "extrapolate multipliers and friction bound from the "
                            "last two increments of a step")
    curvature_tangent: bool = param(False, "", "include the rounded-edge curvature term "
                                    "-A p dn/dx in the contact tangent (exact but indefinite "
                                    "where skin is pinched at a plate edge; see the module "
                                    "docstring)")
    chest_wall_contact: bool = param(True, "", "protocols: no free node may pass behind the "
                                     "chest-wall plane (a frictionless rigid wall at the model's "
                                     "most posterior x: the torso).  Off gives the paper's model, "
                                     "in which the tissue pinched between a plate's rounded edge "
                                     "and the fixed chest wall is squeezed 5 to 12 mm behind that "
                                     "plane (Pelicano exams 03 and 10): inside the torso")
    behind_wall_warn_mm: float = param(10.0, "mm", "reports: warn (log and the step's "
                                       "'warnings') when a node ends a protocol step deeper "
                                       "than this behind the chest-wall plane (the torso is "
                                       "there; see chest_wall_contact); every step reports the "
                                       "depth as behind_chest_wall_mm", gt=0.0)
    edge_band_mm: float = param(10.0, "mm", "reports: the plate force carried by the skin "
                                "that lay (reference configuration) within this distance in "
                                "front of the plate's chest-wall edge, or behind it, is "
                                "reported apart as edge_normal_force_N: the tissue attached "
                                "near the fixed chest wall", ge=0.0)
    penalty_growth: float = param(4.0, "-", "augmented Lagrangian: a node whose violation "
                                  "fell by less than slow_uzawa_ratio in one multiplier update "
                                  "gets its penalty multiplied by this (1: never)", ge=1.0, le=100.0)
    slow_uzawa_ratio: float = param(0.3, "-", "violation ratio between two multiplier updates "
                                    "above which a node's penalty grows", gt=0.0, lt=1.0)
    penalty_growth_max: float = param(256.0, "-", "largest node penalty as a multiple of the "
                                      "automatic one", ge=1.0, le=1e6)
    stalled_uzawa_updates: int = param(2, "-", "augmented Lagrangian: an increment is cut back "
                                       "once its largest violation has fallen by less than 1 % "
                                       "in this many consecutive multiplier updates at the "
                                       "penalty cap (penalty_growth_max): a node the plate "
                                       "pins against the fixed chest wall, whose multiplier "
                                       "only grows (0: never; the increment then runs out its "
                                       "max_augmentations)", ge=0, le=1000)
    retry_penalty_growth_max: float = param(16.0, "-", "protocols: a plate move that does not "
                                            "converge is run once more from its start with "
                                            "penalty_growth_max lowered to this (0: no such "
                                            "retry); see ProtocolRunner._run_step_with_retry",
                                            ge=0.0)
    retry_plate_increment_mm: float = param(5.0, "mm", "protocols: a plate move that crawls "
                                            "([mechanics.solver] crawl_increments) or does not "
                                            "converge is run once more from its start with "
                                            "max_plate_increment_mm lowered to this (half the "
                                            "user's cap if that is smaller; 0: no such retry).  "
                                            "A crawl is retried so first, a non-convergence "
                                            "after the penalty retry", ge=0.0)


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


def _copy(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else a.copy()


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ni,nj->nij", a, b)


class PlateContact:
    """Frictional contact of a set of body nodes against one moving rigid plate.

    Implements :class:`regtrack.mechanics.contributions.Contribution`.

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
        self.use_al = config.method == "augmented-lagrangian"
        self.lagged = config.friction_bound == "multiplier"
        self.curvature = bool(config.curvature_tangent)  # swap_tangent() toggles it
        m = len(self.nodes)
        self.eps_node = np.full(m, self.eps_n)  # node-wise normal penalty (grows, see augment)
        self._viol_last: np.ndarray | None = None  # violation at the last multiplier update
        self._stalled_updates = 0  # consecutive capped updates without progress (augment)
        self.stalled: str = ""  # why the multipliers cannot converge (solver cuts back), or ""
        self.stalled_at: tuple[str, int] | None = None  # (plate, skin node) of that stall
        # committed state (end of the last converged increment)
        self._lam = np.zeros(m)
        self._pconv = np.zeros(m)  # pressure of the last converged increment (MPa)
        self._anchor = self.plate.to_local(self.X[self.nodes])  # stick points, plate-local
        self._hist: list[tuple[float, np.ndarray]] = []  # (t, converged pressure) of this step
        # trial state (current increment / solve)
        self.lam = self._lam.copy()
        self.pbar = self._pconv.copy()  # friction bound pressure of the current solve
        self._t = 0.0
        self._frozen: np.ndarray | None = None  # stick/slip state frozen for the solve
        self._freeze_request = False
        self._fric_resolves = 0  # friction re-solves of the current increment
        self.friction_error_accepted = 0.0  # largest friction error accepted in this step
        self._held: np.ndarray | None = None  # state of the last Newton iterate (line search)
        self._k_pre: sp.csr_matrix | None = None  # see preconditioner_tangent
        self._n_iter = 0
        self._last_x: np.ndarray | None = None
        self._slip_pred: np.ndarray | None = None  # state code of the last increment
        self._plate0 = plate
        self._n_slip = 0
        self.motion: tuple[np.ndarray, np.ndarray] | None = None
        self.counters = {"friction_resolves": 0, "freezes": 0, "penalty_growths": 0}

    # -- state snapshots (protocol engine: retry a plate move) ---------------------------
    def get_state(self) -> dict:
        """Copy of the committed state (plate, stick points, multipliers, pressures)."""
        return {"plate": self.plate, "anchor": self._anchor.copy(), "lam": self._lam.copy(),
                "pconv": self._pconv.copy(), "motion": self.motion, "eps": self.eps_node.copy()}

    def set_state(self, state: dict) -> None:
        """Restore a state returned by :meth:`get_state`."""
        self.plate = self._plate0 = state["plate"]
        self._anchor = state["anchor"].copy()
        self._lam = state["lam"].copy()
        self._pconv = state["pconv"].copy()
        if "eps" in state:
            self.eps_node = state["eps"].copy()
        self.lam = self._lam.copy()
        self.pbar = self._pconv.copy()
        self._hist = []
        self._slip_pred = None
        self._new_solve()
        self.motion = state["motion"]

    def min_gap(self, u: np.ndarray) -> float:
        """Smallest signed gap (mm) of the candidate nodes at displacement ``u`` (N, 3)."""
        x = self.X[self.nodes] + np.asarray(u, float).reshape(-1, 3)[self.nodes]
        return float(self.plate.query(x).gap.min())

    # -- plate motion -----------------------------------------------------------------
    def set_motion(self, start, end) -> None:
        """Move the plate face origin linearly from ``start`` to ``end`` (mm) over t in [0, 1]."""
        self.motion = (np.asarray(start, float).reshape(3), np.asarray(end, float).reshape(3))

    def begin_step(self, step: Any) -> None:
        """Start of a protocol step: the committed plate position is the step's start."""
        self._plate0 = self.plate
        self._hist = [(0.0, self._pconv.copy())]
        self._t = 0.0
        self.friction_error_accepted = 0.0

    def set_time(self, t: float) -> None:
        """Move the plate to its position at ``t``; start a new increment (predictor)."""
        if self.motion is not None:
            a, b = self.motion
            self.plate = self.plate.moved_to(a + float(t) * (b - a))
        self._t = float(t)
        self._viol_last = None
        self._stalled_updates = 0
        self.stalled = ""
        self.stalled_at = None
        self._fric_resolves = 0
        self.lam = self._lam.copy()
        self.pbar = self._pconv.copy()
        if self.config.predictor and len(self._hist) >= 2:
            (t0, p0), (t1, p1) = self._hist[-2:]
            if t1 > t0 and t > t1:
                pred = np.maximum(p1 + (p1 - p0) * (t - t1) / (t1 - t0), 0.0)
                self.pbar = pred
                if self.use_al:
                    # only where the node is pressed now: a separating node keeps lambda
                    self.lam = np.where(self._lam > 0, pred, self._lam)
        self._new_solve()

    def freeze(self) -> None:
        """Solver hook: Newton stagnates (stick/slip chatter).  Freeze the stick/slip state
        at the next iterate for the rest of this solve; :meth:`augment` checks it afterwards
        (the traction is continuous across the stick/slip boundary, so a node frozen near it
        passes the ``friction_tol`` check)."""
        if self.mu > 0 and self._frozen is None:
            self._freeze_request = True

    def swap_tangent(self) -> bool:
        """Switch between the tangent with and without the edge curvature term (see the
        module docstring); the residual does not change."""
        self.curvature = not self.curvature
        return True

    def _new_solve(self) -> None:
        self._freeze_request = False
        self._frozen = None
        self._held = None
        self._n_iter = 0
        self._last_x = None

    # -- the physics ------------------------------------------------------------------
    def _state(self, u: np.ndarray, *, tangent: bool):
        x = self.X[self.nodes] + np.asarray(u, float).reshape(-1, 3)[self.nodes]
        q = self.plate.query(x, curvature=tangent and self.curvature)
        p = self.lam - self.eps_node * q.gap
        act = p > 0
        p = np.where(act, p, 0.0)
        return x, q, p, act

    def _friction(self, x, q, p, act, *, exact: bool = False) -> fr.Traction:
        """Return mapping with the solve's bound and frozen state (``exact``: bound from
        the current pressure, state from the trial)."""
        bound = self.mu * (self.pbar if (self.lagged and not exact) else p)
        return fr.return_map(x, self.plate.to_model(self._anchor), q.normal, act, bound,
                             eps_t=self.eps_t,
                             frozen=None if exact else (self._frozen if self._frozen is not None
                                                        else self._held))

    def nodal_forces(self, u: np.ndarray) -> tuple[np.ndarray, dict]:
        """Contact force on each candidate node (M, 3) in N, and state figures."""
        x, q, p, act = self._state(u, tangent=False)
        f = p[:, None] * q.normal
        nslip = 0
        if self.mu > 0:
            tr = self._friction(x, q, p, act)
            f = f + tr.t
            nslip = int(tr.slip.sum())
        f *= self.areas[:, None]
        pen = float(max(0.0, -q.gap[act].min())) if act.any() else 0.0
        return f, {"active": act, "gap": q.gap, "pressure": p, "n_slip": nslip,
                   "max_penetration_mm": pen}

    def _chatter_control(self, x, q, p, act) -> None:
        """Stick/slip state bookkeeping at each residual evaluation of a solve.

        The solver evaluates the residual at each Newton iterate (with the tangent) and at
        line-search points; an iterate is recognised as a call at the same positions as
        the previous call (the accepted line-search point) or the first call of a solve.
        At an iterate the state is decided by the trial and held for the line search
        (``hold_state_in_line_search``); after ``stick_slip_freeze`` iterates it is frozen
        for the rest of the solve.  :meth:`augment` checks the state afterwards.
        """
        if self.mu <= 0:
            return
        iterate = self._last_x is None or np.array_equal(self._last_x, x)
        self._last_x = x.copy()
        if not iterate or self._frozen is not None:
            return
        self._n_iter += 1
        self._held = None
        if self._n_iter == 1 and self._slip_pred is not None and self.config.slip_predictor:
            self._held = np.where(self._slip_pred == fr.SLIP, fr.SLIP, 0).astype(np.int8)
            return
        n = self.config.stick_slip_freeze
        if self._freeze_request or (n > 0 and self._n_iter > n):
            self._frozen = fr.state_code(self._friction(x, q, p, act))
            self.counters["freezes"] += 1
        elif self.config.hold_state_in_line_search:
            self._held = fr.state_code(self._friction(x, q, p, act))

    def residual_tangent(self, u: np.ndarray) -> tuple[np.ndarray, sp.spmatrix | None]:
        """Residual ``-f`` (3N,) and its tangent (3N, 3N) CSR, or None without contact."""
        ndof = self.X.size
        x, q, p, act = self._state(u, tangent=True)
        res = np.zeros(ndof)
        self._k_pre = None
        if not act.any():
            return res, None
        self._chatter_control(x, q, p, act)
        idx = np.flatnonzero(act)
        A = self.areas[idx]
        n = q.normal[idx]
        H = q.dn_dx[idx] if self.curvature else np.zeros((len(idx), 3, 3))
        pa = p[idx]
        f = pa[:, None] * n
        # normal: r = -A p n ; dr/dx = A (eps n n^T - p H)
        eps = self.eps_node[idx]
        K = A[:, None, None] * (eps[:, None, None] * _outer(n, n) - pa[:, None, None] * H)
        Kp = None  # the tangent less the bound's pressure dependence (preconditioner)
        if self.mu > 0:
            tr = self._friction(x, q, p, act).subset(idx)
            f = f + tr.t
            dB = None if self.lagged else -self.mu * eps[:, None] * n  # dB/dx = mu dp/dx
            Kt = fr.tangent(tr, n, H, eps_t=self.eps_t)
            if dB is not None and tr.slip.any():
                Kp = K + A[:, None, None] * Kt
                Kt = Kt + fr.bound_tangent(tr, dB)  # zero but on slipping nodes
            K = K + A[:, None, None] * Kt
        f = f * A[:, None]
        dof = 3 * self.nodes[idx][:, None] + np.arange(3)[None]
        np.add.at(res, dof.ravel(), -f.ravel())
        rows = np.repeat(dof, 3, axis=1).ravel()
        cols = np.tile(dof, (1, 3)).ravel()
        Kc = sp.csr_matrix((K.ravel(), (rows, cols)), shape=(ndof, ndof))
        if Kp is not None:
            self._k_pre = sp.csr_matrix((Kp.ravel(), (rows, cols)), shape=(ndof, ndof))
        return res, Kc

    def preconditioner_tangent(self) -> sp.spmatrix | None:
        """The last tangent without the sliding nodes' ``ghat (dB/dx)^T`` term, or None
        when there is no such term (solver hook: the matrix the preconditioner factorises).

        Per sliding node the term is ``-A mu eps ghat n^T``: of the order of ``mu`` times
        the normal penalty, far above the tissue's tangential stiffness, and it is the
        only non-symmetric part of the tangent (with ``curvature_tangent = false``).  The
        symmetric part of the tangent, ``(K + K^T) / 2``, spreads it over both triangles
        (``-A mu eps (ghat n^T + n ghat^T) / 2``), which makes a node's block nearly
        indefinite and a poor preconditioner.  Dropped instead, the preconditioned
        operator is ``I + P^{-1} E`` with ``E`` a sum of node-local rank-one terms
        ``ghat n^T``, ``ghat`` orthogonal to ``n``: nearly nilpotent, so GMRES needs few
        iterations."""
        return self._k_pre

    # -- increment bookkeeping --------------------------------------------------------
    def commit(self, u: np.ndarray) -> None:
        """Store the stick points (slip history), multipliers and pressures of a converged
        increment."""
        x, q, p, act = self._state(u, tangent=False)
        new = x.copy()  # off contact: the stick point follows the node
        self._n_slip = 0
        if self.mu > 0 and act.any():
            tr = self._friction(x, q, p, act)
            new = fr.slid_anchor(x, tr, eps_t=self.eps_t)
            self._n_slip = int(tr.slip.sum())
            self._slip_pred = fr.state_code(tr)
        self._anchor = self.plate.to_local(new)
        # augmented Lagrangian: keep the multipliers of the converged solve, so the next
        # increment starts in equilibrium (p = lambda - eps g is unchanged at this u)
        self._lam = self.lam.copy()
        self._pconv = p.copy()
        self.pbar = p.copy()
        self._hist = (self._hist + [(self._t, p.copy())])[-2:]
        self._plate0 = self.plate
        self._new_solve()

    def carry_multipliers(self, u: np.ndarray) -> None:
        """Before :meth:`commit` of an increment that ends before the step does (solver
        ``augmentation = "final"``, no ``augment`` re-solves): one Uzawa update of the
        multipliers, ``lambda <- max(0, lambda - eps g(u)) = p(u)``, which the commit
        carries into the next increment (augmented Lagrangian only).  The solve's frozen
        stick/slip state is dropped, so the commit stores the stick points of the exact
        return mapping at ``u``: that state is not checked here as :meth:`augment` checks
        it."""
        if self.use_al:
            _, _, p, _ = self._state(u, tangent=False)
            self.lam = p.copy()
            self.pbar = p.copy()
        self._new_solve()

    def trial_state(self) -> dict:
        """Copy of the current solve's multipliers, friction bound pressure and held
        stick/slip state (solver: the settle after a stabilised increment starts from the
        stabilised solve's multipliers and, if it fails, returns to that whole state)."""
        return {"lam": self.lam.copy(), "pbar": self.pbar.copy(),
                "frozen": _copy(self._frozen), "held": _copy(self._held)}

    def set_trial_state(self, state: dict, *, solve_state: bool = True) -> None:
        """Restore a :meth:`trial_state`: the multipliers and bound pressure, and with
        ``solve_state`` the frozen / held stick/slip state too (what :meth:`commit` then
        stores is that solve's); without it a new solve starts from those multipliers."""
        self.lam = state["lam"].copy()
        self.pbar = state["pbar"].copy()
        self._new_solve()
        if solve_state:
            self._frozen, self._held = _copy(state["frozen"]), _copy(state["held"])

    def rollback(self) -> None:
        """Forget the trial multipliers and plate position of a cut-back increment."""
        self.lam = self._lam.copy()
        self.pbar = self._pconv.copy()
        self.plate = self._plate0
        self._new_solve()

    def augment(self, u: np.ndarray) -> bool:
        """After a converged solve: update the multipliers (Uzawa ``lambda <- max(0,
        lambda - eps g)``) and the friction bound; True when nothing needs updating.

        Normal: every pressed node lies within ``penetration_tol_mm`` of the plate
        (neither penetrating nor pushed from a distance).  Friction: the forces of the
        solve (lagged bound, frozen state) differ from the exact return mapping at the
        current pressure by at most ``friction_tol`` of ``mu`` times the normal force
        (:func:`regtrack.mechanics.friction.friction_error`).  On False the solver
        re-solves the increment with the updated multipliers / bound / free state.
        """
        x, q, p, act = self._state(u, tangent=False)
        done = True
        if self.use_al:
            v = np.where(act, np.abs(q.gap), 0.0)
            if float(v.max(initial=0.0)) > self.config.penetration_tol_mm:
                c = self.config
                self._check_stall(v)
                if c.penalty_growth > 1.0 and self._viol_last is not None:
                    slow = ((v > c.penetration_tol_mm) & (self._viol_last > 0)
                            & (v > c.slow_uzawa_ratio * self._viol_last))
                    self.eps_node[slow] = np.minimum(self.eps_node[slow] * c.penalty_growth,
                                                     c.penalty_growth_max * self.eps_n)
                    self.counters["penalty_growths"] += int(slow.sum())
                self._viol_last = v
                self.lam = p
                done = False
        if self.mu > 0 and act.any() and (self.lagged or self._frozen is not None
                                          or self._held is not None):
            err = fr.friction_error(self._friction(x, q, p, act),
                                    self._friction(x, q, p, act, exact=True),
                                    self.areas, p, self.mu)
            tol = (self.config.friction_tol if self._fric_resolves < 2
                   else self.config.friction_tol_cycling)
            if err > tol:
                if done:
                    self.counters["friction_resolves"] += 1
                    self._fric_resolves += 1
                done = False
            else:
                self.friction_error_accepted = max(self.friction_error_accepted, err)
        if not done:
            self.pbar = p.copy()
            self._new_solve()
        if log.isEnabledFor(logging.DEBUG) and act.any():
            log.debug("plate '%s': largest gap violation %.3g mm (tolerance %.3g mm), %d nodes in "
                      "contact: %s", self.name, float(np.abs(q.gap[act]).max()),
                      self.config.penetration_tol_mm, int(act.sum()),
                      "accepted" if done else "re-solve (multipliers or friction bound updated)")
        return done

    def _check_stall(self, v: np.ndarray) -> None:
        """Uzawa stall: the worst node's violation ``v`` (mm) fell by less than 1 % since the
        last multiplier update although its penalty is at the cap, ``stalled_uzawa_updates``
        times in a row; sets :attr:`stalled` (the solver then cuts the increment back).

        Seen on the benchmark hemisphere's CC (9.5k nodes): a skin node 2.5 mm in front of
        the fixed chest wall, under the rounded plate edge, stayed 5.000 mm deep while its
        multiplier rose by 29 MPa at every update for 15 re-solves (2-4 Newton iterations
        each), after which the increment failed all the same."""
        c = self.config
        if c.stalled_uzawa_updates <= 0 or self._viol_last is None:
            return
        i = int(np.argmax(v))
        capped = self.eps_node[i] >= c.penalty_growth_max * self.eps_n * (1.0 - 1e-12)
        if capped and v[i] > 0.99 * self._viol_last[i]:
            self._stalled_updates += 1
        else:
            self._stalled_updates = 0
        if self._stalled_updates >= c.stalled_uzawa_updates:
            self.stalled_at = (self.name, int(self.nodes[i]))
            self.stalled = (f"augmented-Lagrangian multipliers stalled on plate '{self.name}': skin node "
                            f"{int(self.nodes[i])} stays {v[i]:.3g} mm deep at the penalty cap")

    def report(self, u: np.ndarray) -> dict:
        """Plate force (N), maximum penetration (mm), active nodes, contact area (mm^2).

        ``edge_normal_force_N`` is the part of ``normal_force_N`` carried by the skin that,
        in the reference configuration, lies behind the plate's chest-wall edge or within
        ``edge_band_mm`` in front of it (plate-local ``s`` of the reference position below
        the edge's ``s`` plus the band): the tissue attached near the fixed chest wall,
        wherever the compression has moved it.

        Call after :meth:`commit`; ``n_slip`` counts the nodes that slid in the increment
        just committed.
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
                "n_slip": self._n_slip,
                "contact_area_mm2": float(self.areas[act].sum()),
                "friction_error_max": self.friction_error_accepted,
                "plate_origin_mm": self.plate.origin.tolist()}
