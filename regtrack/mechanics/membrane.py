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

_D2DET = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
_DTR = np.array([1.0, 1.0, 0.0])


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


def _invariant_derivatives(c: np.ndarray):
    """I1, I2 and their gradients/Hessians wrt c = (C11, C22, C12), vectorised."""
    C11, C22, C12 = c[:, 0], c[:, 1], c[:, 2]
    tr = C11 + C22
    d = C11 * C22 - C12 * C12
    dd = np.stack([C22, C11, -2.0 * C12], axis=1)
    inv = 1.0 / d
    dinv = -dd * (inv * inv)[:, None]
    d2inv = 2.0 * np.einsum("ti,tj->tij", dd, dd) * (inv**3)[:, None, None] - _D2DET[None] * (inv**2)[:, None, None]
    I1 = tr + inv
    I2 = d + tr * inv
    g1 = _DTR[None] + dinv
    g2 = dd + _DTR[None] * inv[:, None] + tr[:, None] * dinv
    h1 = d2inv
    outer = np.einsum("i,tj->tij", _DTR, dinv)
    h2 = _D2DET[None] + outer + outer.transpose(0, 2, 1) + tr[:, None, None] * d2inv
    return I1, I2, g1, g2, h1, h2


def membrane_forces(x: np.ndarray, tris: np.ndarray, G: np.ndarray, A0: np.ndarray,
                    mat: SkinMaterial, *, want_k: bool) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Nodal forces per triangle (T, 3, 3), element tangents (T, 9, 9) or None, energy (N mm).

    Raises ``FloatingPointError`` when a triangle degenerates (det C <= 0).
    """
    X = x[tris]  # (T, 3 nodes, 3)
    F = _surface_gradient(X, G)  # (T, 3, 2)
    c = np.stack([np.einsum("ti,ti->t", F[:, :, 0], F[:, :, 0]),
                  np.einsum("ti,ti->t", F[:, :, 1], F[:, :, 1]),
                  np.einsum("ti,ti->t", F[:, :, 0], F[:, :, 1])], axis=1)
    if np.any(c[:, 0] * c[:, 1] - c[:, 2] ** 2 <= 0):
        raise FloatingPointError("degenerate skin triangle (det C <= 0)")
    I1, I2, g1, g2, h1, h2 = _invariant_derivatives(c)
    a, b = I1 - 3.0, I2 - 3.0
    psi = mat.c10 * a + mat.c01 * b + mat.c11 * a * b + mat.c20 * a * a + mat.c02 * b * b
    psi1 = mat.c10 + mat.c11 * b + 2.0 * mat.c20 * a
    psi2 = mat.c01 + mat.c11 * a + 2.0 * mat.c02 * b
    w = A0 * mat.thickness
    gpsi = psi1[:, None] * g1 + psi2[:, None] * g2  # (T, 3)
    hpsi = None
    if mat.wrinkling:
        psi, gpsi, hpsi = _relax(c, psi, gpsi, mat, want_k=want_k)
    # Dc[t, m, a, i]: derivative of c_m wrt x_{a,i}
    Ga0, Ga1 = G[:, :, 0], G[:, :, 1]
    F0, F1 = F[:, :, 0], F[:, :, 1]
    Dc = np.empty((len(tris), 3, 3, 3))
    Dc[:, 0] = 2.0 * Ga0[:, :, None] * F0[:, None, :]
    Dc[:, 1] = 2.0 * Ga1[:, :, None] * F1[:, None, :]
    Dc[:, 2] = Ga0[:, :, None] * F1[:, None, :] + Ga1[:, :, None] * F0[:, None, :]
    fe = w[:, None, None] * np.einsum("tm,tmai->tai", gpsi, Dc)
    energy = float(np.sum(w * psi))
    if not want_k:
        return fe, None, energy
    taut = (2.0 * mat.c20) * np.einsum("ti,tj->tij", g1, g1) + (2.0 * mat.c02) * np.einsum("ti,tj->tij", g2, g2) \
        + mat.c11 * (np.einsum("ti,tj->tij", g1, g2) + np.einsum("ti,tj->tij", g2, g1)) \
        + psi1[:, None, None] * h1 + psi2[:, None, None] * h2
    hpsi = taut if hpsi is None else np.where(np.isnan(hpsi[:, :1, :1]), taut, hpsi)
    Dc2 = Dc.reshape(len(tris), 3, 9)
    Ke = _sandwich(Dc2, np.ascontiguousarray(hpsi))
    S = (2.0 * gpsi[:, 0, None, None] * Ga0[:, :, None] * Ga0[:, None, :]
         + 2.0 * gpsi[:, 1, None, None] * Ga1[:, :, None] * Ga1[:, None, :]
         + gpsi[:, 2, None, None] * (Ga0[:, :, None] * Ga1[:, None, :] + Ga1[:, :, None] * Ga0[:, None, :]))
    Ke = Ke.reshape(len(tris), 3, 3, 3, 3)  # (t, a, i, b, k)
    for i in range(3):  # + S_ab delta_ik
        Ke[:, :, i, :, i] += S
    Ke = Ke.reshape(len(tris), 9, 9) * w[:, None, None]
    return fe, Ke, energy


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


@njit(cache=True)
def _sandwich(D, H):
    """``K[t, A, B] = sum_m sum_n D[t, m, A] H[t, m, n] D[t, n, B]`` (T, 9, 9).

    The same products, summed in the same order (m outer, n inner, from 0), as numpy's
    ``einsum("tmA,tmn,tnB->tAB")`` that it replaces: bit-identical on the benchmark
    hemisphere's CC path, and 1.1 against 9.3 ms for its 4,490 skin triangles."""
    nt, nm, na = D.shape
    out = np.empty((nt, na, na))
    for t in range(nt):
        for A in range(na):
            for B in range(na):
                s = 0.0
                for m in range(nm):
                    for n in range(nm):
                        s += D[t, m, A] * H[t, m, n] * D[t, n, B]
                out[t, A, B] = s
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


def _relax(c: np.ndarray, psi: np.ndarray, gpsi: np.ndarray, mat: SkinMaterial, *, want_k: bool):
    """Pipkin's relaxed energy (module docstring): ``psi``, ``dpsi/dc`` (T, 3) and, for the
    wrinkled and slack triangles, ``d2psi/dc2`` (T, 3, 3) (NaN rows: taut, the caller's)."""
    C11, C22, C12 = c[:, 0], c[:, 1], c[:, 2]
    dlt = C11 - C22
    q = np.sqrt(dlt * dlt + 4.0 * C12 * C12)
    m1 = 0.5 * (C11 + C22 + q)
    m2 = 0.5 * (C11 + C22 - q)
    _, d, _ = _psi_mu(m1, m2, mat)
    loose = d[1] < 0.0
    hpsi = np.full((len(c), 3, 3), np.nan) if want_k else None
    if not loose.any():
        return psi, gpsi, hpsi
    psi, gpsi = psi.copy(), gpsi.copy()
    slack = loose & (m1 <= 1.0)
    wr = np.flatnonzero(loose & ~slack)
    psi[slack] = 0.0
    gpsi[slack] = 0.0
    if want_k:
        hpsi[slack] = 0.0
    if len(wr) == 0:
        return psi, gpsi, hpsi
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
    qq = np.maximum(q[wr], 1e-300)
    dl, c12 = dlt[wr], C12[wr]
    dm1 = np.stack([0.5 * (1.0 + dl / qq), 0.5 * (1.0 - dl / qq), 2.0 * c12 / qq], axis=1)  # dmu1/dc
    psi[wr] = f
    gpsi[wr] = fp[:, None] * dm1
    if want_k:
        fpp = hh[0] - hh[1] ** 2 / hh[2]
        dq = np.stack([dl / qq, -dl / qq, 4.0 * c12 / qq], axis=1)
        e = np.array([1.0, -1.0, 0.0])
        d_dq = (e[None] - (dl / qq)[:, None] * dq) / qq[:, None]  # d(dlt/q)/dc
        d_cq = (np.array([0.0, 0.0, 1.0])[None] - (c12 / qq)[:, None] * dq) / qq[:, None]  # d(C12/q)/dc
        H1 = np.stack([0.5 * d_dq, -0.5 * d_dq, 2.0 * d_cq], axis=1)  # H1[t, m, n] = d2mu1/dc_m dc_n
        hpsi[wr] = fpp[:, None, None] * np.einsum("ti,tj->tij", dm1, dm1) + fp[:, None, None] * H1
    return psi, gpsi, hpsi
