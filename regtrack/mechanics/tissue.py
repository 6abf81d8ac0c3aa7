r"""Element kernels of the nearly incompressible neo-Hookean tetrahedron (numba).

Strain energy per unit reference volume (see :mod:`.materials`)

.. math:: W = c_1(J^{-2/3} I_1 - 3) + U(J),\qquad U = \tfrac{K}{2}(J-1)^2 .

First Piola-Kirchhoff stress, with :math:`H = F^{-T}` and pressure :math:`p`

.. math:: P = 2c_1 J^{-2/3}\,(F - \tfrac{I_1}{3} H) + p\,J\,H ,

where ``p = K (J - 1)`` for the plain P1 formulation and ``p = \bar p_e`` (the mean of
the nodal pressures of the element's nodes) for the average-nodal-pressure (ANP)
tetrahedron of Bonet & Burton (1998) / Bonet, Marriott & Hassan (2001).  The element
tangent is :math:`K^e_{ab,ik} = V_e \sum_{JL} G_{aJ} A_{iJkL} G_{bL}` with

.. math::
    A = 2c_1 J^{-2/3}\big[\delta_{ik}\delta_{JL} - \tfrac23 (H_{kL}F_{iJ} + F_{kL}H_{iJ})
        + \tfrac29 I_1 H_{iJ}H_{kL} + \tfrac{I_1}{3} H_{kJ}H_{iL}\big]
        + (p' J + p) J H_{iJ}H_{kL} - p J H_{kJ}H_{iL},

``p' = dp/dJ`` (``K`` for P1; 0 in the element part of ANP, whose volumetric rank
term enters through the augmented system, :mod:`.problem`).  ``G`` are the reference shape-function
gradients (1/mm), ``V_e`` the reference volume (mm^3).  Units: mm, N, MPa.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from regtrack.mechanics import parallel


def reference_geometry(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape-function gradients ``G`` (E, 4, 3) in 1/mm and volumes ``V`` (E,) in mm^3."""
    p = points[tets]
    D = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns
    V = np.linalg.det(D) / 6.0
    Dinv = np.linalg.inv(D)  # rows = gradients of N1..N3
    G = np.empty((len(tets), 4, 3))
    G[:, 1:, :] = Dinv
    G[:, 0, :] = -Dinv.sum(axis=1)
    return G, V


@njit(cache=True)
def _defgrad(x, tets, G, e, F):
    for i in range(3):
        for J in range(3):
            s = 0.0
            for a in range(4):
                s += x[tets[e, a], i] * G[e, a, J]
            F[i, J] = s


@njit(cache=True)
def _det3(F):
    return (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
            - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
            + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))


@njit(cache=True)
def _inv_transpose(F, J, H):
    H[0, 0] = (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]) / J
    H[0, 1] = (F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]) / J
    H[0, 2] = (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]) / J
    H[1, 0] = (F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]) / J
    H[1, 1] = (F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]) / J
    H[1, 2] = (F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]) / J
    H[2, 0] = (F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]) / J
    H[2, 1] = (F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]) / J
    H[2, 2] = (F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) / J


@njit(cache=True, nogil=True)
def jacobians_part(x, tets, G, out, elems, owned):
    """``out[e] = det F`` for the elements of ``elems`` whose first node is ``owned``
    (one :class:`regtrack.mechanics.parallel.Part`; every element has one such part)."""
    F = np.empty((3, 3))
    for e in elems:
        if owned[tets[e, 0]]:
            _defgrad(x, tets, G, e, F)
            out[e] = _det3(F)


def jacobians(x: np.ndarray, tets: np.ndarray, G: np.ndarray, parts=None) -> np.ndarray:
    """Volume ratio ``J = det F`` (E,) of every tetrahedron at current positions ``x``
    (over the threads of ``parts``, :func:`regtrack.mechanics.parallel.node_partition`)."""
    out = np.empty(len(tets))
    parts = parts or parallel.node_partition(len(x), tets, 1)
    parallel.run_parts(jacobians_part, (x, tets, G, out), parts)
    return out


@njit(cache=True, nogil=True)
def tet_kernel(x, tets, G, V, c1, p, dp, want_k, project, f, data, base, rowstride, dv, ee, elems,
               owned):
    """Accumulate internal forces and optionally the tangent over one thread's part.

    The part (:class:`regtrack.mechanics.parallel.Part`) is ``elems`` (increasing) and
    ``owned`` (N,) bool: only the rows of owned nodes are written, and each element's
    energy and inversion are counted by the part that owns its first node, so that the
    parts together give the serial loop's values bit for bit (see :mod:`.parallel`).

    Parameters
    ----------
    x : (N, 3) current positions (mm).
    p, dp : (E,) pressure (MPa) and dp/dJ (MPa) per element (see module docstring).
    want_k : assemble the tangent into ``data`` (CSR values) at
        ``base[e, a, b] + i * rowstride[tets[e, a]] + k``.
    project : assemble each element's tangent with its material tangent ``A`` (9x9,
        module docstring) projected onto the positive semi-definite cone (its negative
        eigenvalues set to zero, as Teran et al. 2005), so that the assembled tangent is
        positive semi-definite whatever the deformation: ``K^e = V_e B^T A^+ B`` with
        ``B`` the map from nodal displacements to ``dF`` (:func:`_projected_tangent`:
        ``A``'s eigensystem in closed form).  An element whose ``A`` has no negative
        eigenvalue keeps its consistent tangent.
    f : (N, 3) forces (N), accumulated in place.
    dv : (E, 4, 3) output: derivative of the current element volume wrt node positions
        (mm^2), used by the ANP rank term.
    ee : (E,) output: deviatoric energy of each element (N mm; 0 if inverted).

    Returns
    -------
    n_inverted : count of this part's elements with J <= 0.
    """
    F = np.empty((3, 3))
    H = np.empty((3, 3))
    fa = np.empty((4, 3))
    ha = np.empty((4, 3))
    Ke = np.empty((12, 12))
    work = np.empty((7, 3, 3))
    bad = 0
    for e in elems:
        counts = owned[tets[e, 0]]
        _defgrad(x, tets, G, e, F)
        J = _det3(F)
        if J <= 0.0:
            if counts:
                bad += 1
                ee[e] = 0.0
            continue
        I1, Jm23, mu_e = point_state(F, J, c1[e], G[e], H, fa, ha)
        if counts:
            ee[e] = V[e] * c1[e] * (Jm23 * I1 - 3.0)
        pe = p[e]
        for a in range(4):
            n = tets[e, a]
            if not owned[n]:
                continue
            for i in range(3):
                f[n, i] += V[e] * force_entry(fa, ha, a, i, mu_e, I1, pe, J)
                dv[e, a, i] = V[e] * J * ha[a, i]
        if not want_k:
            continue
        cvol = (dp[e] * J + pe) * J
        cgeo = mu_e * I1 / 3.0 - pe * J
        if not (project and _projected_tangent(G, e, F, J, I1, mu_e, pe * J, cvol, V[e], Ke, work)):
            _element_tangent(G, e, fa, ha, mu_e, I1, cvol, cgeo, V[e], Ke)
        for a in range(4):
            na = tets[e, a]
            if owned[na]:
                rs = rowstride[na]
                for b in range(4):
                    b0 = base[e, a, b]
                    for i in range(3):
                        for k in range(3):
                            data[b0 + i * rs + k] += Ke[3 * a + i, 3 * b + k]
    return bad


@njit(cache=True, inline="always")
def point_state(F, J, c1, Ga, H, fa, ha):
    """The neo-Hookean state at one point, shared by the P1 and P2 kernels.

    From the deformation gradient ``F`` with ``J = det F > 0``, the material's ``c1``
    (MPa) and the shape-function gradients ``Ga`` (n, 3) 1/mm of the element's n nodes,
    fills ``H = F^-T`` and ``fa[a] = F G_a``, ``ha[a] = H G_a`` (n, 3), and returns
    ``(I1, J^(-2/3), mu_e)`` with ``I1 = tr(F^T F)`` and ``mu_e = 2 c1 J^(-2/3)`` (MPa).
    """
    _inv_transpose(F, J, H)
    I1 = 0.0
    for i in range(3):
        for j in range(3):
            I1 += F[i, j] * F[i, j]
    Jm23 = J ** (-2.0 / 3.0)
    mu_e = 2.0 * c1 * Jm23
    for a in range(Ga.shape[0]):
        for i in range(3):
            sf = 0.0
            sh = 0.0
            for L in range(3):
                sf += F[i, L] * Ga[a, L]
                sh += H[i, L] * Ga[a, L]
            fa[a, i] = sf
            ha[a, i] = sh
    return I1, Jm23, mu_e


@njit(cache=True, inline="always")
def force_entry(fa, ha, a, i, mu_e, I1, p, J):
    """``(P G_a)_i`` of the module docstring at one point (MPa/mm): the first Piola-Kirchhoff
    stress applied to node ``a``'s gradient, from :func:`point_state`'s ``fa``, ``ha``,
    ``mu_e``, ``I1`` and the pressure ``p`` (MPa)."""
    return mu_e * (fa[a, i] - I1 / 3.0 * ha[a, i]) + p * J * ha[a, i]


@njit(cache=True, inline="always")
def tangent_entry(fa, ha, a, b, i, k, mu_e, I1, cvol, cgeo, gg):
    """``sum_JL G_aJ A_iJkL G_bL`` of the module docstring at one point (MPa/mm^2), from
    ``fa = F G_a``, ``ha = H G_a``, ``gg = G_a . G_b``, ``mu_e = 2 c1 J^(-2/3)`` and the
    volumetric and geometric coefficients ``cvol = (p' J + p) J``, ``cgeo = mu_e I1 / 3 - p J``."""
    v = (mu_e * (-2.0 / 3.0 * (fa[a, i] * ha[b, k] + ha[a, i] * fa[b, k])
                 + 2.0 / 9.0 * I1 * ha[a, i] * ha[b, k])
         + cvol * ha[a, i] * ha[b, k] + cgeo * ha[a, k] * ha[b, i])
    if i == k:
        v += mu_e * gg
    return v


@njit(cache=True)
def _element_tangent(G, e, fa, ha, mu_e, I1, cvol, cgeo, Ve, Ke):
    """The element tangent (12, 12) N/mm of :func:`tet_kernel` (module docstring) into ``Ke``."""
    for a in range(4):
        for b in range(4):
            gg = 0.0
            for L in range(3):
                gg += G[e, a, L] * G[e, b, L]
            for i in range(3):
                for k in range(3):
                    Ke[3 * a + i, 3 * b + k] = Ve * tangent_entry(fa, ha, a, b, i, k, mu_e, I1,
                                                                  cvol, cgeo, gg)


@njit(cache=True)
def _eigh3(C, w, Q):
    """Eigenvalues ``w`` (3,) and orthonormal eigenvectors (the columns of ``Q``) of the
    symmetric 3x3 ``C`` by cyclic Jacobi rotations (to round-off; ``C`` is overwritten)."""
    for i in range(3):
        for j in range(3):
            Q[i, j] = 1.0 if i == j else 0.0
    for _ in range(30):
        off = C[0, 1] ** 2 + C[0, 2] ** 2 + C[1, 2] ** 2
        if off <= 1e-36 * (C[0, 0] ** 2 + C[1, 1] ** 2 + C[2, 2] ** 2) or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if C[p, q] == 0.0:
                continue
            theta = (C[q, q] - C[p, p]) / (2.0 * C[p, q])
            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # C <- C R
                a, b = C[k, p], C[k, q]
                C[k, p], C[k, q] = c * a - s * b, s * a + c * b
            for k in range(3):  # C <- R^T C
                a, b = C[p, k], C[q, k]
                C[p, k], C[q, k] = c * a - s * b, s * a + c * b
            for k in range(3):
                a, b = Q[k, p], Q[k, q]
                Q[k, p], Q[k, q] = c * a - s * b, s * a + c * b
    for i in range(3):
        w[i] = C[i, i]


@njit(cache=True)
def _projected_tangent(G, e, F, J, I1, mu_e, pJ, cvol, Ve, Ke, work):
    r"""The element tangent with its material tangent projected onto the positive
    semi-definite cone, from ``A``'s eigensystem in closed form; False (``Ke`` untouched)
    when ``A`` has no negative eigenvalue, or when a singular value of ``F`` rounds to
    zero (a degenerate element: the caller's consistent tangent, and the minimiser's shift
    if the Hessian stays indefinite).  The eigenvalues need only the singular values, so
    ``U`` is formed only for an element that is projected.

    The energy at fixed pressure is isotropic, a function of the singular values ``s_i``
    of ``F = U diag(s) V^T``: ``Psi = c1 (J^{-2/3} I1 - 3) + U_p(J)``.  Its Hessian in
    ``F`` has the nine eigenpairs of Smith, de Goes & Kim (2019, *ACM TOG* 38(2) 12): per
    pair ``(i, j)`` a twist ``U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2`` and a flip
    ``U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2`` with

    .. math::
        \lambda_{twist} = \frac{\psi_i + \psi_j}{s_i + s_j}
            = \mu_e \Big(1 - \frac{I_1}{3 s_i s_j}\Big) + \frac{pJ}{s_i s_j},\quad
        \lambda_{flip} = \frac{\psi_i - \psi_j}{s_i - s_j}
            = \mu_e \Big(1 + \frac{I_1}{3 s_i s_j}\Big) - \frac{pJ}{s_i s_j}

    (``psi_i = dPsi/ds_i``, ``mu_e = 2 c1 J^{-2/3}``), and three scaling modes ``U diag(q)
    V^T`` with ``q`` the eigenvectors of the 3x3 Hessian in ``s``

    .. math::
        h_{ij} = \mu_e\Big[\delta_{ij}\big(1 + \tfrac{I_1}{3 s_i^2}\big)
            - \tfrac23\big(\tfrac{s_i}{s_j} + \tfrac{s_j}{s_i}\big)
            + \tfrac29 \tfrac{I_1}{s_i s_j}\Big] + \frac{c_{vol}}{s_i s_j}
            - \delta_{ij}\frac{pJ}{s_i^2}

    (``c_vol = (p' J + p) J``).  ``K^e = V_e sum_m max(lambda_m, 0) w_m w_m^T`` with
    ``w_m[3 a + i] = (M_m G_a)_i``.  ``work``: (7, 3, 3) scratch.
    """
    C, Vm, Um, hq, tmp = work[0], work[1], work[2], work[3], work[4]
    sv, lam_h = work[5, 0], work[5, 1]
    for i in range(3):  # C = F^T F
        for j in range(3):
            v = 0.0
            for k in range(3):
                v += F[k, i] * F[k, j]
            C[i, j] = v
    _eigh3(C, sv, Vm)
    for i in range(3):
        sv[i] = np.sqrt(max(sv[i], 0.0))
    if sv[0] * sv[1] * sv[2] <= 0.0:
        return False
    # the eigenvalues
    negative = False
    pairs = ((0, 1), (0, 2), (1, 2))
    lam_tf = work[6]  # row 0: twist, row 1: flip of pair k
    for k in range(3):
        i, j = pairs[k]
        r = 1.0 / (sv[i] * sv[j])
        lam_tf[0, k] = mu_e * (1.0 - I1 / 3.0 * r) + pJ * r
        lam_tf[1, k] = mu_e * (1.0 + I1 / 3.0 * r) - pJ * r
        negative = negative or lam_tf[0, k] < 0.0 or lam_tf[1, k] < 0.0
    for i in range(3):
        for j in range(3):
            v = mu_e * (-2.0 / 3.0 * (sv[i] / sv[j] + sv[j] / sv[i]) + 2.0 / 9.0 * I1 / (sv[i] * sv[j])) \
                + cvol / (sv[i] * sv[j])
            if i == j:
                v += mu_e * (1.0 + I1 / (3.0 * sv[i] * sv[i])) - pJ / (sv[i] * sv[i])
            tmp[i, j] = v
    _eigh3(tmp, lam_h, hq)
    for m in range(3):
        negative = negative or lam_h[m] < 0.0
    if not negative:
        return False
    # V right-handed (a valid eigenvector basis still), then U = F V / s, orthonormalised
    Vm[0, 2] = Vm[1, 0] * Vm[2, 1] - Vm[2, 0] * Vm[1, 1]
    Vm[1, 2] = Vm[2, 0] * Vm[0, 1] - Vm[0, 0] * Vm[2, 1]
    Vm[2, 2] = Vm[0, 0] * Vm[1, 1] - Vm[1, 0] * Vm[0, 1]
    for m in range(3):
        for i in range(3):
            v = 0.0
            for k in range(3):
                v += F[i, k] * Vm[k, m]
            Um[i, m] = v
    n0 = np.sqrt(Um[0, 0] ** 2 + Um[1, 0] ** 2 + Um[2, 0] ** 2)
    for i in range(3):
        Um[i, 0] /= n0
    d = Um[0, 0] * Um[0, 1] + Um[1, 0] * Um[1, 1] + Um[2, 0] * Um[2, 1]
    for i in range(3):
        Um[i, 1] -= d * Um[i, 0]
    n1 = np.sqrt(Um[0, 1] ** 2 + Um[1, 1] ** 2 + Um[2, 1] ** 2)
    for i in range(3):
        Um[i, 1] /= n1
    Um[0, 2] = Um[1, 0] * Um[2, 1] - Um[2, 0] * Um[1, 1]
    Um[1, 2] = Um[2, 0] * Um[0, 1] - Um[0, 0] * Um[2, 1]
    Um[2, 2] = Um[0, 0] * Um[1, 1] - Um[1, 0] * Um[0, 1]
    # K^e = V_e sum_m max(lambda_m, 0) w_m w_m^T
    for r in range(12):
        for q in range(12):
            Ke[r, q] = 0.0
    w = np.empty(12)
    ga = np.empty((4, 3))  # V^T G_a
    for a in range(4):
        for m in range(3):
            v = 0.0
            for L in range(3):
                v += Vm[L, m] * G[e, a, L]
            ga[a, m] = v
    c = 1.0 / np.sqrt(2.0)
    for mode in range(9):
        if mode < 3:
            lam = lam_h[mode]
        elif mode < 6:
            lam = lam_tf[0, mode - 3]
        else:
            lam = lam_tf[1, mode - 6]
        if lam <= 0.0:
            continue
        for a in range(4):
            for ii in range(3):
                if mode < 3:
                    v = 0.0
                    for k in range(3):
                        v += Um[ii, k] * hq[k, mode] * ga[a, k]
                else:
                    i, j = pairs[(mode - 3) % 3]
                    sgn = -1.0 if mode < 6 else 1.0
                    v = c * (Um[ii, i] * ga[a, j] + sgn * Um[ii, j] * ga[a, i])
                w[3 * a + ii] = v
        lv = Ve * lam
        for r in range(12):
            wr = lv * w[r]
            for q in range(12):
                Ke[r, q] += wr * w[q]
    return True


@njit(cache=True)
def ordered_sum(v):
    """``sum(v)`` accumulated left to right (the serial kernel's order)."""
    s = 0.0
    for i in range(v.shape[0]):
        s += v[i]
    return s
