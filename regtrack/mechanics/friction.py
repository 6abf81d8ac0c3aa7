"""Regularised Coulomb friction of nodes on a rigid plate: return mapping and tangent.

Pure functions used by :class:`regtrack.mechanics.contact.PlateContact`.  A contact
node at ``x`` (mm) with stick point ``a`` (committed at the end of the last converged
increment) and plate normal ``n`` has the elastic tangential slip

.. math::

    g_T = (I - n n^T)(x - a), \\qquad t^{trial} = -\\varepsilon_T\\, g_T

and the traction (MPa) of the return mapping (Wriggers, *Computational Contact
Mechanics*, 2nd ed., ch. 5; Laursen, *Computational Contact and Impact Mechanics*, 2002)

.. math::

    t = \\begin{cases} t^{trial} & \\varepsilon_T |g_T| \\le B \\ \\text{(stick)} \\\\
        -B\\, g_T / |g_T| & \\text{otherwise (slip)} \\end{cases}

with the slip bound ``B = mu p`` (MPa).  Two choices of ``p`` are offered:

* ``"current"``: the pressure at the current iterate, ``p(x)``; the consistent tangent
  then has the non-symmetric term ``-mu ghat (dp/dx)^T`` and every Newton iterate can
  change both the bound and the stick/slip set (the slow case of issue 5).
* ``"multiplier"`` (Simo & Laursen, *Comput. Struct.* 42, 1992, "an augmented
  Lagrangian treatment of contact problems involving friction"): the bound uses the
  pressure ``pbar`` of the last converged solve (the augmented normal multiplier), held
  fixed while Newton iterates; the friction problem inside one solve is then of Tresca
  type (bound independent of ``x``), whose slip tangent ``(B/|g_T|)(I - ghat ghat^T)
  dg_T/dx`` is symmetric on the flat plate face.  ``pbar`` is updated after each
  converged solve until the friction forces it implies agree with those of the exact
  bound (:func:`friction_error`), nested with the augmented-Lagrangian updates.

Stick/slip chatter control: after a few Newton iterations of a solve the state of each
node may be frozen (``frozen``: 1 stick, 2 slip, 0 decided by the trial); the frozen
problem is smooth, and the state is checked against the exact return mapping after
convergence (:func:`friction_error`), a wrong state costing one more solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STICK, SLIP = 1, 2


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ni,nj->nij", a, b)


@dataclass
class Traction:
    """Frictional traction of the candidate nodes (model frame).

    Attributes
    ----------
    t : (M, 3) float
        Tangential traction (MPa).
    stick, slip : (M,) bool
        State masks (both False off contact).
    ghat : (M, 3) float
        Unit slip direction ``g_T / |g_T|`` (zero where ``g_T = 0``).
    gt : (M, 3) float
        Elastic tangential slip ``g_T`` (mm).
    gn : (M,) float
        ``|g_T|`` (mm).
    d : (M, 3) float
        ``x - a`` (mm).
    bound : (M,) float
        Slip bound ``B`` (MPa), zero off contact.
    """

    t: np.ndarray
    stick: np.ndarray
    slip: np.ndarray
    ghat: np.ndarray
    gt: np.ndarray
    gn: np.ndarray
    d: np.ndarray
    bound: np.ndarray

    def subset(self, idx: np.ndarray) -> Traction:
        """The tractions of the nodes ``idx`` only."""
        return Traction(**{k: getattr(self, k)[idx] for k in
                           ("t", "stick", "slip", "ghat", "gt", "gn", "d", "bound")})


#: Width of the band around the slip bound in which a held (frozen) stick/slip state is kept.
FREEZE_HYSTERESIS = 2.0


def return_map(x: np.ndarray, anchor: np.ndarray, normal: np.ndarray, active: np.ndarray,
               bound: np.ndarray, *, eps_t: float, frozen: np.ndarray | None = None) -> Traction:
    """Stick/slip return mapping (see the module docstring).

    Parameters
    ----------
    x, anchor, normal : (M, 3) float
        Node positions, stick points (mm) and plate normals.
    active : (M,) bool
        Nodes in normal contact (``p > 0``).
    bound : (M,) float
        Slip bound ``B = mu p`` (MPa).
    eps_t : float
        Tangential (stick) penalty (MPa/mm).
    frozen : (M,) int, optional
        Imposed state (:data:`STICK`, :data:`SLIP`, 0 = decided by the trial).
    """
    d = x - anchor
    gt = d - normal * np.einsum("ni,ni->n", normal, d)[:, None]
    gn = np.linalg.norm(gt, axis=1)
    B = np.where(active, np.maximum(bound, 0.0), 0.0)
    stick = eps_t * gn <= B
    if frozen is not None:
        # held state with a hysteresis band: a held node keeps its state while its trial
        # force eps_T |g_T| stays within [B / h, h B] of the bound (no chatter at the
        # boundary), and changes state beyond it (a node held as slipping whose g_T
        # shrinks to ~0 would have a slip direction of round-off and a tangent B / |g_T|)
        h = FREEZE_HYSTERESIS
        stick = np.where(frozen == STICK, eps_t * gn <= h * B,
                         np.where(frozen == SLIP, eps_t * gn <= B / h, stick))
    stick &= active
    slip = active & ~stick & (gn > 0)
    ghat = gt / np.where(gn > 0, gn, 1.0)[:, None]
    ghat[gn <= 0] = 0.0
    t = np.zeros_like(x)
    t[stick] = -eps_t * gt[stick]
    t[slip] = -B[slip, None] * ghat[slip]
    return Traction(t=t, stick=stick, slip=slip, ghat=ghat, gt=gt, gn=gn, d=d, bound=B)


def tangent(tr: Traction, normal: np.ndarray, dn_dx: np.ndarray, *, eps_t: float) -> np.ndarray:
    """Derivative of the traction ``-t`` with respect to the node position (M, 3, 3), MPa/mm,
    at a fixed slip bound ``B`` (add :func:`bound_tangent` when ``B`` depends on the position).

    ``dg_T/dx = (I - n n^T) - (n.d) dn/dx - n (dn/dx d)^T``; stick: ``eps_T dg_T/dx``;
    slip: ``(B/|g_T|)(I - ghat ghat^T) dg_T/dx``.
    """
    n = normal
    nd = np.einsum("ni,ni->n", n, tr.d)
    P = np.eye(3)[None] - _outer(n, n)
    dgt = P - nd[:, None, None] * dn_dx - _outer(n, np.einsum("nij,nj->ni", dn_dx, tr.d))
    K = np.zeros((len(n), 3, 3))
    K[tr.stick] = eps_t * dgt[tr.stick]
    sl = tr.slip
    if sl.any():
        gh = tr.ghat[sl]
        proj = np.eye(3)[None] - _outer(gh, gh)
        K[sl] = (tr.bound[sl] / tr.gn[sl])[:, None, None] * np.einsum("nij,njk->nik", proj, dgt[sl])
    return K


def bound_tangent(tr: Traction, dbound_dx: np.ndarray) -> np.ndarray:
    """The slip tangent's term from a position-dependent bound (M, 3, 3), MPa/mm:
    ``ghat (dB/dx)^T`` on the slipping nodes (``dbound_dx`` (M, 3), the ``"current"``
    bound), zero elsewhere."""
    K = np.zeros((len(dbound_dx), 3, 3))
    sl = tr.slip
    K[sl] = _outer(tr.ghat[sl], dbound_dx[sl])
    return K


def slid_anchor(x: np.ndarray, tr: Traction, *, eps_t: float) -> np.ndarray:
    """Stick points after a converged increment (mm, model frame).

    Sticking nodes keep theirs (``x - d``); slipping nodes drag theirs to
    ``x - (B / eps_T) ghat`` so that ``|g_T| = B / eps_T`` (slip history); off contact
    the stick point follows the node (``x``).
    """
    a = x.copy()
    a[tr.stick] = x[tr.stick] - tr.d[tr.stick]
    a[tr.slip] = x[tr.slip] - (tr.bound[tr.slip] / eps_t)[:, None] * tr.ghat[tr.slip]
    return a


def state_code(tr: Traction) -> np.ndarray:
    """(M,) int8: :data:`STICK`, :data:`SLIP` or 0 (off contact)."""
    out = np.zeros(len(tr.stick), np.int8)
    out[tr.stick] = STICK
    out[tr.slip] = SLIP
    return out


def friction_error(used: Traction, exact: Traction, areas: np.ndarray, pressure: np.ndarray,
                   mu: float) -> float:
    """Error of the friction forces of a converged solve, relative to ``mu`` times the normal force.

    .. math:: e = \\frac{\\sum_i A_i |t_i^{used} - t_i^{exact}|}{\\mu \\sum_i A_i p_i}

    ``used``: traction with the lagged bound and frozen state of the solve; ``exact``:
    return mapping with the bound of the current pressure, state from the trial.  ``e``
    bounds the relative error of the total friction force against Coulomb's ``mu N``.
    """
    ref = mu * float(np.sum(areas * pressure))
    if ref <= 0:
        return 0.0
    diff = np.linalg.norm(used.t - exact.t, axis=1)
    return float(np.sum(areas * diff)) / ref
