r"""Skin: incompressible plane-stress hyperelastic membrane on the outer-surface triangles.

Each linear triangle (reference area :math:`A_0`, thickness :math:`H`) has the in-plane
deformation gradient :math:`F = \sum_a x_a \otimes G_a` (3x2, ``G_a`` the reference
in-plane shape-function gradients) and :math:`C = F^T F` (2x2).  Incompressibility
fixes the thickness stretch :math:`\lambda_3^2 = 1/\det C`, so

.. math:: I_1 = \operatorname{tr} C + \frac{1}{\det C},\qquad
          I_2 = \det C + \frac{\operatorname{tr} C}{\det C},

and the energy is :math:`A_0 H\,\Psi(I_1, I_2)` with the polynomial (N = 2) model

.. math:: \Psi = c_{10}(I_1-3) + c_{01}(I_2-3) + c_{11}(I_1-3)(I_2-3)
                 + c_{20}(I_1-3)^2 + c_{02}(I_2-3)^2 .

Forces and the consistent tangent follow by the chain rule through the three
independent components ``c = (C11, C22, C12)``.  In principal stretches the Cauchy
stress is :math:`\sigma_i = 2(\lambda_i^2-\lambda_3^2)\Psi_1 - 2(\lambda_i^{-2}-\lambda_3^{-2})\Psi_2`
(used by the tests as the independent reference).  Units: mm, N, MPa.

**Wrinkling (tension-field theory).**  A membrane has no bending stiffness, so it cannot
carry compression: it wrinkles.  With ``SkinMaterial.wrinkling`` the energy is Pipkin's
relaxed energy (Pipkin 1986, IMA J. Appl. Math. 36; as used for wrinkling membranes by
Roddeman et al. 1987).  With :math:`\mu_1 \ge \mu_2` the eigenvalues of ``C`` (squared
in-plane principal stretches) and :math:`\Psi_{,2} = \partial\Psi/\partial\mu_2`:

* taut, :math:`\Psi_{,2}(\mu_1, \mu_2) \ge 0`: :math:`\Psi` as above;
* wrinkled, :math:`\Psi_{,2} < 0` and :math:`\mu_1 > 1`:
  :math:`\Psi_r = f(\mu_1) = \Psi(\mu_1, \mu_2^*(\mu_1))` with the natural width
  :math:`\mu_2^*` solving :math:`\Psi_{,2}(\mu_1, \mu_2^*) = 0` (Newton; for the
  Mooney-Rivlin part :math:`\mu_2^* = \mu_1^{-1/2}`).  The stress is uniaxial along the
  first principal direction, :math:`S = 2 f'(\mu_1) N_1 \otimes N_1` with
  :math:`f' = \Psi_{,1}` (envelope theorem), and
  :math:`f'' = \Psi_{,11} - \Psi_{,12}^2 / \Psi_{,22}`;
* slack, :math:`\Psi_{,2} < 0` and :math:`\mu_1 \le 1`: no energy, stress or stiffness.

The three branches meet with continuous energy and stress.  ``c -> mu_1`` is the closed-form
eigenvalue :math:`\mu_1 = (\operatorname{tr} C + \sqrt{(C_{11}-C_{22})^2 + 4C_{12}^2})/2`,
whose Hessian carries the rotation of the wrinkle direction, so the tangent stays consistent
(tested against finite differences).  Without it, a compressed skin triangle has negative
stiffness (its compressive stress enters the geometric term), the tangent of the whole model
is indefinite wherever the plates push skin together, and Newton wanders: on the phantom's
MLO compression the membrane alone turned a 76-iteration solve into 579 iterations or a stop.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from regtrack.mechanics.materials import SkinMaterial

def reference_geometry(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane shape gradients ``G`` (T, 3, 2) (1/mm) and reference areas ``A0`` (T,) (mm^2)."""
    p = points[tris]
    a1 = p[:, 1] - p[:, 0]
    a2 = p[:, 2] - p[:, 0]
    nrm = np.cross(a1, a2)
    area2 = np.linalg.norm(nrm, axis=1)
    e1 = a1 / np.linalg.norm(a1, axis=1)[:, None]
    n = nrm / area2[:, None]
    e2 = np.cross(n, e1)
    D = np.empty((len(tris), 2, 2))  # columns: local coords of edges
    D[:, 0, 0] = np.einsum("ij,ij->i", a1, e1)
    D[:, 1, 0] = np.einsum("ij,ij->i", a1, e2)
    D[:, 0, 1] = np.einsum("ij,ij->i", a2, e1)
    D[:, 1, 1] = np.einsum("ij,ij->i", a2, e2)
    Dinv = np.linalg.inv(D)
    G = np.empty((len(tris), 3, 2))
    G[:, 1:, :] = Dinv
    G[:, 0, :] = -Dinv.sum(axis=1)
    return G, 0.5 * area2


def membrane_forces(x: np.ndarray, tris: np.ndarray, G: np.ndarray, A0: np.ndarray,
                    mat: SkinMaterial, *, want_k: bool) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Nodal forces per triangle (T, 3, 3), element tangents (T, 9, 9) or None, energy (N mm).

    Raises ``FloatingPointError`` when a triangle degenerates (det C <= 0).

    The per-triangle algebra runs in numba kernels (:func:`_metric`, :func:`_taut`,
    :func:`_element`), each operation in the order of the numpy expressions they replaced,
    so the results are bit-identical to them (checked on the benchmark hemisphere's CC
    states; the Newton path of the protocols depends on the last digit).  ``inv**3`` stays
    a numpy power (its vectorised ``pow`` may round differently from numba's), and the
    wrinkled triangles' Newton solve (:func:`_relax`) stays in numpy.  Benchmark hemisphere
    (4,490 skin triangles, 3,445 of them wrinkled or slack at its compressed CC state): 2.6
    ms with the tangent (of which ``_relax`` 0.9 ms, ``_element`` 1.3 ms) and 0.95 ms
    without, against 6.7 and 2.5 ms for the equivalent numpy code.
    """
    X = x[tris]  # (T, 3 nodes, 3)
    F = _surface_gradient(X, G)  # (T, 3, 2)
    c, inv = _metric(F)
    if np.any(np.isnan(inv)):
        raise FloatingPointError("degenerate skin triangle (det C <= 0)")
    inv3 = inv**3 if want_k else inv[:0]
    coef = np.array([mat.c10, mat.c01, mat.c11, mat.c20, mat.c02])
    psi, gpsi, psi12, g12, h12 = _taut(c, inv, inv3, coef, want_k, mat.wrinkling)
    w = A0 * mat.thickness
    loose = np.zeros(len(tris), np.bool_)
    hpsi = np.zeros((0, 3, 3))
    if mat.wrinkling:
        loose = psi12[:, 2] < 0.0  # Psi_2 < 0 at (mu_1, mu_2): wrinkled or slack
        if loose.any():
            hpsi = _relax(c, psi, gpsi, psi12[:, 3], loose, mat, want_k=want_k)
    energy = float(np.sum(w * psi))
    fe, Ke = _element(F, G, w, gpsi, psi12, g12, h12, coef, loose, hpsi, want_k)
    return fe, (Ke if want_k else None), energy


@njit(cache=True, nogil=True)
def _metric(F):
    """``c = (C11, C22, C12)`` (T, 3) of ``C = F^T F`` and ``1 / det C`` (T,), NaN where
    ``det C <= 0``."""
    nt = F.shape[0]
    c = np.empty((nt, 3))
    inv = np.empty(nt)
    for t in range(nt):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for i in range(3):
            s0 += F[t, i, 0] * F[t, i, 0]
            s1 += F[t, i, 1] * F[t, i, 1]
            s2 += F[t, i, 0] * F[t, i, 1]
        c[t, 0] = s0
        c[t, 1] = s1
        c[t, 2] = s2
        d = s0 * s1 - s2 * s2
        inv[t] = 1.0 / d if d > 0.0 else np.nan
    return c, inv


@njit(cache=True, nogil=True)
def _taut(c, inv, inv3, coef, want_k, wrinkling):
    """The taut (unrelaxed) energy of each triangle: ``psi`` (T,), ``dpsi/dc`` (T, 3), and
    ``psi12`` (T, 4) = (Psi_1, Psi_2 in the invariants; Psi_2 in mu_2 and mu_1 of the
    relaxation test, :func:`_relax`), ``g12`` (T, 2, 3) the gradients of I1 and I2 in ``c``
    and, with ``want_k``, ``h12`` (T, 2, 3, 3) their Hessians.  ``inv3`` is ``inv**3``."""
    c10, c01, c11, c20, c02 = coef[0], coef[1], coef[2], coef[3], coef[4]
    nt = c.shape[0]
    psi = np.empty(nt)
    gpsi = np.empty((nt, 3))
    psi12 = np.zeros((nt, 4))
    g12 = np.empty((nt, 2, 3))
    h12 = np.empty((nt, 2, 3, 3) if want_k else (0, 2, 3, 3))
    dtr = (1.0, 1.0, 0.0)
    d2det = ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, -2.0))
    dd = np.empty(3)
    dinv = np.empty(3)
    for t in range(nt):
        C11, C22, C12 = c[t, 0], c[t, 1], c[t, 2]
        tr = C11 + C22
        d = C11 * C22 - C12 * C12
        dd[0] = C22
        dd[1] = C11
        dd[2] = -2.0 * C12
        iv = inv[t]
        iv2 = iv * iv
        for m in range(3):
            dinv[m] = -dd[m] * iv2
        I1 = tr + iv
        I2 = d + tr * iv
        for m in range(3):
            g12[t, 0, m] = dtr[m] + dinv[m]
            g12[t, 1, m] = dd[m] + dtr[m] * iv + tr * dinv[m]
        if want_k:
            for i in range(3):
                for j in range(3):
                    d2 = 2.0 * (dd[i] * dd[j]) * inv3[t] - d2det[i][j] * iv2
                    h12[t, 0, i, j] = d2
                    h12[t, 1, i, j] = d2det[i][j] + dtr[i] * dinv[j] + dtr[j] * dinv[i] + tr * d2
        a = I1 - 3.0
        b = I2 - 3.0
        psi[t] = c10 * a + c01 * b + c11 * a * b + c20 * a * a + c02 * b * b
        p1 = c10 + c11 * b + 2.0 * c20 * a
        p2 = c01 + c11 * a + 2.0 * c02 * b
        psi12[t, 0] = p1
        psi12[t, 1] = p2
        for m in range(3):
            gpsi[t, m] = p1 * g12[t, 0, m] + p2 * g12[t, 1, m]
        if wrinkling:  # Psi_2 in the squared principal stretches (as _psi_mu computes it)
            dlt = C11 - C22
            q = np.sqrt(dlt * dlt + 4.0 * C12 * C12)
            m1 = 0.5 * (C11 + C22 + q)
            m2 = 0.5 * (C11 + C22 - q)
            J1 = m1 + m2 + 1.0 / (m1 * m2)
            J2 = 1.0 / m1 + 1.0 / m2 + m1 * m2
            ra, rb = J1 - 3.0, J2 - 3.0
            r1 = c10 + c11 * rb + 2.0 * c20 * ra
            r2 = c01 + c11 * ra + 2.0 * c02 * rb
            psi12[t, 2] = r1 * (1.0 - 1.0 / (m1 * m2 * m2)) + r2 * (m1 - 1.0 / (m2 * m2))
            psi12[t, 3] = m1
    return psi, gpsi, psi12, g12, h12


@njit(cache=True, nogil=True)
def _element(F, G, w, gpsi, psi12, g12, h12, coef, loose, hpsi, want_k):
    """Nodal forces ``fe`` (T, 3, 3) and, with ``want_k``, tangents ``Ke`` (T, 9, 9): ``Dc``
    (the derivative of ``c`` in the nodal positions), ``fe = w gpsi . Dc``, ``Ke = w (Dc^T
    H Dc + S (x) I)`` with ``H = d2psi/dc2`` (the taut one, or ``hpsi`` where ``loose``)
    and ``S`` the second Piola-Kirchhoff stress in the shape gradients (geometric term)."""
    c11, c20, c02 = coef[2], coef[3], coef[4]
    nt = F.shape[0]
    fe = np.empty((nt, 3, 3))
    Ke = np.empty((nt, 9, 9) if want_k else (0, 9, 9))
    Dc = np.empty((3, 9))
    H = np.empty((3, 3))
    S = np.empty((3, 3))
    for t in range(nt):
        for a in range(3):
            for i in range(3):
                Dc[0, 3 * a + i] = 2.0 * G[t, a, 0] * F[t, i, 0]
                Dc[1, 3 * a + i] = 2.0 * G[t, a, 1] * F[t, i, 1]
                Dc[2, 3 * a + i] = G[t, a, 0] * F[t, i, 1] + G[t, a, 1] * F[t, i, 0]
        for A in range(9):
            s = 0.0
            for m in range(3):
                s += gpsi[t, m] * Dc[m, A]
            fe[t, A // 3, A % 3] = w[t] * s
        if not want_k:
            continue
        if loose[t]:
            for m in range(3):
                for n in range(3):
                    H[m, n] = hpsi[t, m, n]
        else:
            p1, p2 = psi12[t, 0], psi12[t, 1]
            for m in range(3):
                for n in range(3):
                    g1m, g1n = g12[t, 0, m], g12[t, 0, n]
                    g2m, g2n = g12[t, 1, m], g12[t, 1, n]
                    H[m, n] = ((2.0 * c20) * (g1m * g1n) + (2.0 * c02) * (g2m * g2n)
                               + c11 * (g1m * g2n + g2m * g1n)
                               + p1 * h12[t, 0, m, n] + p2 * h12[t, 1, m, n])
        for a in range(3):
            for b in range(3):
                S[a, b] = (2.0 * gpsi[t, 0] * G[t, a, 0] * G[t, b, 0]
                           + 2.0 * gpsi[t, 1] * G[t, a, 1] * G[t, b, 1]
                           + gpsi[t, 2] * (G[t, a, 0] * G[t, b, 1] + G[t, a, 1] * G[t, b, 0]))
        for A in range(9):
            for B in range(9):
                s = 0.0
                for m in range(3):
                    for n in range(3):
                        s += Dc[m, A] * H[m, n] * Dc[n, B]
                if A % 3 == B % 3:
                    s += S[A // 3, B // 3]
                Ke[t, A, B] = s * w[t]
    return fe, Ke


@njit(cache=True)
def _surface_gradient(X, G):
    """``F[t, i, J] = sum_a X[t, a, i] G[t, a, J]`` (T, 3, 2), summed over ``a`` in order as
    numpy's ``einsum("tai,taJ->tiJ")`` that it replaces (0.02 ms against einsum's 1.0 ms
    on the benchmark hemisphere's 4,490 skin triangles)."""
    nt = X.shape[0]
    out = np.empty((nt, 3, 2))
    for t in range(nt):
        for i in range(3):
            for J in range(2):
                s = 0.0
                for a in range(3):
                    s += X[t, a, i] * G[t, a, J]
                out[t, i, J] = s
    return out


def _psi_mu(m1: np.ndarray, m2: np.ndarray, mat: SkinMaterial):
    """Psi and its first and second derivatives in the squared principal stretches
    (mu_1, mu_2), with mu_3 = 1 / (mu_1 mu_2)."""
    I1 = m1 + m2 + 1.0 / (m1 * m2)
    I2 = 1.0 / m1 + 1.0 / m2 + m1 * m2
    a, b = I1 - 3.0, I2 - 3.0
    psi = mat.c10 * a + mat.c01 * b + mat.c11 * a * b + mat.c20 * a * a + mat.c02 * b * b
    p1 = mat.c10 + mat.c11 * b + 2.0 * mat.c20 * a
    p2 = mat.c01 + mat.c11 * a + 2.0 * mat.c02 * b
    i1 = (1.0 - 1.0 / (m1 * m1 * m2), 1.0 - 1.0 / (m1 * m2 * m2))  # dI1/dmu_k
    i2 = (m2 - 1.0 / (m1 * m1), m1 - 1.0 / (m2 * m2))  # dI2/dmu_k
    i1h = (2.0 / (m1 ** 3 * m2), 1.0 / (m1 * m1 * m2 * m2), 2.0 / (m1 * m2 ** 3))  # 11, 12, 22
    i2h = (2.0 / m1 ** 3, np.ones_like(m1), 2.0 / m2 ** 3)
    d = (p1 * i1[0] + p2 * i2[0], p1 * i1[1] + p2 * i2[1])

    def second(k, l, h):
        return (2.0 * mat.c20 * i1[k] * i1[l] + 2.0 * mat.c02 * i2[k] * i2[l]
                + mat.c11 * (i1[k] * i2[l] + i2[k] * i1[l]) + p1 * i1h[h] + p2 * i2h[h])

    return psi, d, (second(0, 0, 0), second(0, 1, 1), second(1, 1, 2))


def _relax(c: np.ndarray, psi: np.ndarray, gpsi: np.ndarray, m1: np.ndarray, loose: np.ndarray,
           mat: SkinMaterial, *, want_k: bool) -> np.ndarray:
    """Pipkin's relaxed energy (module docstring) of the ``loose`` triangles (``Psi_2 < 0``
    at their principal stretches, :func:`_taut`; ``m1`` (T,) the larger eigenvalue of
    ``C``): sets their ``psi`` and ``dpsi/dc`` (T, 3) in place and returns ``d2psi/dc2``
    (T, 3, 3), whose rows count for the loose triangles only (:func:`_element`)."""
    hpsi = np.zeros((len(c), 3, 3))
    slack = loose & (m1 <= 1.0)
    wr = np.flatnonzero(loose & ~slack)
    psi[slack] = 0.0
    gpsi[slack] = 0.0
    if len(wr) == 0:
        return hpsi
    C11, C22, C12 = c[wr, 0], c[wr, 1], c[wr, 2]
    dl = C11 - C22
    q = np.sqrt(dl * dl + 4.0 * C12 * C12)
    u1 = m1[wr]
    u2 = 1.0 / np.sqrt(u1)  # natural width of the Mooney-Rivlin part
    for _ in range(30):  # Newton on Psi_2(mu_1, mu_2) = 0 (convex in mu_2 near the root)
        _, dd, hh = _psi_mu(u1, u2, mat)
        step = dd[1] / hh[2]
        u2 = np.clip(u2 - step, 0.25 * u2, 4.0 * u2)
        if np.all(np.abs(step) <= 1e-13 * u2):
            break
    f, dd, hh = _psi_mu(u1, u2, mat)
    fp = dd[0]
    qq = np.maximum(q, 1e-300)
    dm1 = np.stack([0.5 * (1.0 + dl / qq), 0.5 * (1.0 - dl / qq), 2.0 * C12 / qq], axis=1)  # dmu1/dc
    psi[wr] = f
    gpsi[wr] = fp[:, None] * dm1
    if want_k:
        fpp = hh[0] - hh[1] ** 2 / hh[2]
        dq = np.stack([dl / qq, -dl / qq, 4.0 * C12 / qq], axis=1)
        e = np.array([1.0, -1.0, 0.0])
        d_dq = (e[None] - (dl / qq)[:, None] * dq) / qq[:, None]  # d(dlt/q)/dc
        d_cq = (np.array([0.0, 0.0, 1.0])[None] - (C12 / qq)[:, None] * dq) / qq[:, None]  # d(C12/q)/dc
        H1 = np.stack([0.5 * d_dq, -0.5 * d_dq, 2.0 * d_cq], axis=1)  # H1[t, m, n] = d2mu1/dc_m dc_n
        hpsi[wr] = fpp[:, None, None] * np.einsum("ti,tj->tij", dm1, dm1) + fp[:, None, None] * H1
    return hpsi
