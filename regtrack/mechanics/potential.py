"""Rigid-plate contact and friction as potentials: the plate terms of the incremental
potential that :mod:`.minimise` minimises.

A skin node ``i`` (tributary reference area ``A_i``, mm^2) meets a rigid plate
(:mod:`.plates`: signed gap ``g_i(x)`` in mm, outward unit normal ``n_i``).

**Normal contact**, augmented Lagrangian (method of multipliers; Bertsekas 1982), with the
multiplier ``lambda_i`` (MPa) and the penalty ``eps_i`` (MPa/mm):

.. math::

    \\Pi_N = \\sum_i \\frac{A_i}{2\\varepsilon_i} \\max(0, \\lambda_i - \\varepsilon_i g_i)^2
    \\quad\\text{(N mm)},\\qquad
    \\frac{\\partial \\Pi_N}{\\partial x_i} = -A_i p_i n_i,\\quad
    p_i = \\max(0, \\lambda_i - \\varepsilon_i g_i),

    \\frac{\\partial^2 \\Pi_N}{\\partial x_i^2} = A_i \\varepsilon_i n_i n_i^T [p_i > 0]
    - A_i p_i \\frac{\\partial n_i}{\\partial x_i}.

The plate is convex, so ``dn/dx`` (non-zero only on its rounded edges) is positive
semi-definite and acts on the plane orthogonal to ``n``: the second term is the negative
part of the node's 3x3 block and is left out.  That is the block's projection onto the
positive semi-definite cone (eigenvalue clamping), so the Hessian handed to Newton is
positive semi-definite; the gradient stays exact.

**Friction**, lagged (Simo & Laursen 1992; Li et al. 2020, *Incremental Potential
Contact*, section 5): with the stick point ``a_i`` (committed at the end of the last
increment and carried with the plate), the lagged normal ``nbar_i`` and slip bound ``B_i =
mu pbar_i`` (``pbar``: the lagged pressure, :meth:`PlatePotential.update`), the tangential
slip ``s_i = |T_i (x_i - a_i)|``, ``T_i = I - nbar_i nbar_i^T``, enters a C2 friction
potential (the cubic mollifier of IPC's ``f_1``, scaled so that sliding starts at the slip
``delta_i = B_i / eps_T``; ``r = s / delta``)

.. math::

    \\Pi_T = \\sum_i A_i \\varphi(s_i),\\qquad
    \\varphi(s) = \\begin{cases} B \\delta (r^2 - r^3/3) & r < 1 \\\\
    B (s - \\delta / 3) & r \\ge 1, \\end{cases}\\qquad
    \\varphi'(s) = B (2 \\bar r - \\bar r^2),\\quad \\bar r = \\min(r, 1),

convex in ``x``.  Its gradient is ``A_i varphi'(s_i) ghat_i`` (``ghat = T (x - a) / s``,
the traction: ``eps_T``-scaled stick, saturating at the Coulomb bound ``B`` at ``s =
delta``) and its Hessian ``A_i [varphi'' ghat ghat^T + (varphi' / s)(T - ghat ghat^T)]``
with ``varphi'' = 2 eps_T (1 - r)^+`` and ``varphi' / s = eps_T (2 - r)`` while sticking,
both non-negative.  The traction is C1 in the slip: the Hessian does not jump between
stick and slip (a piecewise-linear Huber traction does, and Newton then alternates a node
between the two states without converging).  The minimiser iterates the lag to
consistency (``pbar = p``, ``nbar = n``) in every increment, so the converged state obeys
Coulomb's law at the current pressure.

Units: mm, N, MPa (N/mm^2); energies in N mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

#: Smallest relaxation of the multiplier and friction-lag updates (:meth:`PlatePotential.update`).
OMEGA_MIN = 0.05


def normal_terms(gap: np.ndarray, normal: np.ndarray, lam: np.ndarray, eps: np.ndarray,
                 areas: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Augmented-Lagrangian normal contact of ``M`` nodes: ``(energy N mm, gradient (M, 3) N,
    projected Hessian blocks (M, 3, 3) N/mm, pressure (M,) MPa)`` (module docstring)."""
    p = np.maximum(lam - eps * gap, 0.0)
    energy = float(np.sum(areas * p * p / (2.0 * eps)))
    grad = -(areas * p)[:, None] * normal
    k = np.where(p > 0, areas * eps, 0.0)
    hess = k[:, None, None] * np.einsum("ni,nj->nij", normal, normal)
    return energy, grad, hess, p


def friction_terms(x: np.ndarray, anchor: np.ndarray, nbar: np.ndarray, bound: np.ndarray,
                   eps_t: float, areas: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Lagged C2 friction of ``M`` nodes at positions ``x`` with stick points ``anchor``
    (mm, model frame), lagged normals ``nbar`` and slip bounds ``bound`` (MPa):
    ``(energy N mm, gradient (M, 3) N, Hessian blocks (M, 3, 3) N/mm, slip mask (M,))``."""
    T = np.eye(3)[None] - np.einsum("ni,nj->nij", nbar, nbar)
    gt = np.einsum("nij,nj->ni", T, x - anchor)
    s = np.linalg.norm(gt, axis=1)
    B = np.maximum(bound, 0.0)
    delta = B / eps_t
    r = np.divide(s, delta, out=np.full_like(s, np.inf), where=delta > 0)
    slip = (r >= 1.0) & (B > 0)
    rc = np.minimum(r, 1.0)
    phi = np.where(slip, B * (s - delta / 3.0), B * delta * (rc * rc - rc ** 3 / 3.0))
    phi = np.where(B > 0, phi, 0.0)
    energy = float(np.sum(areas * phi))
    ghat = gt / np.where(s > 0, s, 1.0)[:, None]
    force = np.where(B > 0, B * (2.0 * rc - rc * rc), 0.0)
    grad = (areas * force)[:, None] * ghat
    d2 = np.where(slip | (B <= 0), 0.0, 2.0 * eps_t * (1.0 - rc))          # varphi''
    tang = np.where(B <= 0, 0.0, np.where(slip, B / np.where(s > 0, s, 1.0),
                                          eps_t * (2.0 - rc)))              # varphi' / s
    gg = np.einsum("ni,nj->nij", ghat, ghat)
    hess = areas[:, None, None] * (d2[:, None, None] * gg + tang[:, None, None] * (T - gg))
    return energy, grad, hess, slip


def slid_anchor(x: np.ndarray, anchor: np.ndarray, nbar: np.ndarray, bound: np.ndarray,
                eps_t: float) -> np.ndarray:
    """Stick points after a converged increment (mm, model frame): the tangential slip is
    kept where a node sticks and shortened to ``B / eps_T`` where it slips (slip history);
    a node without a bound (off contact) takes its own position."""
    T = np.eye(3)[None] - np.einsum("ni,nj->nij", nbar, nbar)
    gt = np.einsum("nij,nj->ni", T, x - anchor)
    s = np.linalg.norm(gt, axis=1)
    B = np.maximum(bound, 0.0)
    scale = np.where(eps_t * s > B, B / (eps_t * np.where(s > 0, s, 1.0)), 1.0)
    scale = np.where(B > 0, scale, 0.0)
    return x - scale[:, None] * gt


@dataclass
class PlateEval:
    """One plate's terms at a state: energy (N mm), force on the body's dofs as a residual
    ``dPi/du`` (3N,) N, Hessian (3N, 3N) COO or None, and per node pressure (MPa), gap (mm)
    and normal."""

    energy: float
    grad: np.ndarray
    hess: sp.coo_matrix | None
    pressure: np.ndarray
    gap: np.ndarray
    normal: np.ndarray


class PlatePotential:
    """The potential of one :class:`~.contact.PlateContact` inside a minimisation.

    It holds the lagged quantities of the current solve (multipliers ``lam``, bound
    pressures ``pbar``, normals ``nbar``, node penalties ``eps``) and the stick points
    (plate-local, so they move with the plate), taken from the contact's committed state
    by :meth:`begin` and written back by :meth:`commit`.  The plate's position is the
    contact's (``PlateContact.set_time`` moves it).
    """

    def __init__(self, contact: Any, u: np.ndarray):
        self.c = contact
        self.begin(u)

    @property
    def name(self) -> str:
        return self.c.name

    def begin(self, u: np.ndarray) -> None:
        """Lagged state from the contact's committed state; normals at ``u`` (N, 3)."""
        st = self.c.get_state()
        self.lam = st["lam"].copy()
        self.pbar = st["pconv"].copy()
        self.eps = np.asarray(st.get("eps", self.c.eps_node), float).copy()
        self.anchor_local = st["anchor"].copy()
        self.nbar = self.c.plate.query(self.positions(u)).normal
        self._step: tuple[np.ndarray, float] | None = None  # the last update's r and omega

    def positions(self, u: np.ndarray) -> np.ndarray:
        return self.c.X[self.c.nodes] + np.asarray(u, float).reshape(-1, 3)[self.c.nodes]

    def evaluate(self, u: np.ndarray, *, hessian: bool) -> PlateEval:
        """Energy, gradient and (projected) Hessian of normal contact and friction at ``u``."""
        c = self.c
        x = self.positions(u)
        q = c.plate.query(x)
        A = c.areas
        e, g, H, p = normal_terms(q.gap, q.normal, self.lam, self.eps, A)
        if c.mu > 0 and np.any(self.pbar > 0):
            anchor = c.plate.to_model(self.anchor_local)
            ef, gf, Hf, _ = friction_terms(x, anchor, self.nbar, c.mu * self.pbar, c.eps_t, A)
            e, g, H = e + ef, g + gf, H + Hf
        ndof = c.X.size
        grad = np.zeros(ndof)
        dof = 3 * c.nodes[:, None] + np.arange(3)[None]
        grad[dof.ravel()] = g.ravel()  # one row per node: no repeated dofs
        K = None
        if hessian:
            live = np.flatnonzero(np.abs(H).reshape(len(H), -1).max(axis=1) > 0)
            d = dof[live]
            rows = np.repeat(d, 3, axis=1).ravel()
            cols = np.tile(d, (1, 3)).ravel()
            K = sp.coo_matrix((H[live].ravel(), (rows, cols)), shape=(ndof, ndof))
        return PlateEval(e, grad, K, p, q.gap, q.normal)

    def max_violation(self, ev: PlateEval) -> float:
        """Deepest penetration of a node carrying pressure (mm)."""
        act = ev.pressure > 0
        return float(max(0.0, -ev.gap[act].min())) if act.any() else 0.0

    def friction_error(self, ev: PlateEval, floor_n: float = 0.0) -> float:
        """``sum_i A_i mu |p_i - pbar_i| / (mu max(sum_i A_i p_i, floor_n))``: the error of
        the lagged slip bound against Coulomb's at the current pressure, relative to the
        plate's normal force or, when the plate barely touches, to ``floor_n`` (N; the
        step's load scale, against which equilibrium itself is judged).  0 without
        friction."""
        c = self.c
        ref = max(float(np.sum(c.areas * ev.pressure)), floor_n)
        if c.mu <= 0 or ref <= 0:
            return 0.0
        return self.friction_force_error(ev) / (c.mu * ref)

    def friction_force_error(self, ev: PlateEval) -> float:
        """``mu sum_i A_i |p_i - pbar_i|`` (N): the lagged slip bound's error as a force,
        by which the next lag update changes the tangential forces (0 without friction)."""
        c = self.c
        if c.mu <= 0:
            return 0.0
        return c.mu * float(np.sum(c.areas * np.abs(ev.pressure - self.pbar)))

    def update(self, ev: PlateEval, *, growth: float, slow_ratio: float, eps_max: float,
               previous: np.ndarray | None) -> np.ndarray:
        """Relaxed multiplier and lag update, and penalty growth.

        With ``r = p - lam`` the step of the plain update ``T`` (Uzawa's ``lam <- p``; the
        lag's ``pbar <- p``), the multipliers and the bound pressures move by ``omega r``
        and ``nbar <- n``.  ``omega`` is Aitken's dynamic relaxation (Irons & Tuck 1969;
        Kuettler & Wall 2008, *Comput. Mech.* 43:61), from the last two steps of the
        increment in the area-weighted inner product,

        .. math::

            \\omega_k = -\\omega_{k-1} \\frac{(r_{k-1}, r_k - r_{k-1})}{(r_k - r_{k-1},
            r_k - r_{k-1})},

        the secant estimate ``1 / (1 - mu)`` of the relaxation that cancels the
        iteration's dominant eigenvalue ``mu``, clipped to ``[OMEGA_MIN, 1]`` (1 at the
        first update of an increment, ``previous is None``): the update only ever damps
        ``T``, half-way for a 2-cycle (``mu = -1``), and a plain update that converges is
        left as it is.  Every such iteration has the fixed points of ``T`` (``lam = pbar =
        p``: the constraint and Coulomb's law at the current pressure).  The method of
        multipliers is firmly nonexpansive for convex problems and never overshoots, but
        the plates' rounded edges (the space outside a convex plate is not convex) and the
        friction lag are not: on a breast compressed to D = 50 % the plain update sends
        the nodes pinched on the upper plate's chest-wall edge into a 2-cycle of lift-off
        and penetration that does not damp out.

        A node whose violation fell by less than ``slow_ratio`` since the last update gets
        ``eps <- min(growth eps, eps_max)`` (the method of multipliers' rule for a
        constraint that converges slowly).  Returns the violations ``max(0, -g)`` (M,)
        before the update."""
        viol = np.where(ev.pressure > 0, np.maximum(-ev.gap, 0.0), 0.0)
        if previous is not None and growth > 1:
            slow = (viol > 0) & (viol > slow_ratio * previous)
            self.eps = np.where(slow, np.minimum(self.eps * growth, eps_max), self.eps)
        r = ev.pressure - self.lam
        omega = 1.0
        if previous is not None and self._step is not None:
            r0, w0 = self._step
            dr = r - r0
            den = float(np.sum(self.c.areas * dr * dr))
            if den > 0:
                omega = -w0 * float(np.sum(self.c.areas * r0 * dr)) / den
            omega = min(max(omega, OMEGA_MIN), 1.0)
        self._step = (r, omega)
        self.lam = np.maximum(self.lam + omega * r, 0.0)
        self.pbar = np.maximum(self.pbar + omega * (ev.pressure - self.pbar), 0.0)
        self.nbar = ev.normal.copy()
        return viol

    def commit(self, u: np.ndarray) -> None:
        """Store the converged increment in the contact: stick points slid by the slip of
        the increment, multipliers and pressures (the next increment starts from them), and
        the number of nodes that slid (``n_slip`` of the contact's report)."""
        c = self.c
        x = self.positions(u)
        anchor = c.plate.to_model(self.anchor_local)
        n_slip = 0
        if c.mu > 0:
            bound = c.mu * self.pbar
            slip = friction_terms(x, anchor, self.nbar, bound, c.eps_t, c.areas)[3]
            n_slip = int(np.count_nonzero(slip & (bound > 0)))
            x = slid_anchor(x, anchor, self.nbar, bound, c.eps_t)
        self.anchor_local = c.plate.to_local(x)
        st = c.get_state()
        st.update(anchor=self.anchor_local.copy(), lam=self.lam.copy(), pconv=self.pbar.copy(),
                  eps=self.eps.copy(), plate=c.plate)
        c.set_state(st)
        c.n_slip = n_slip
