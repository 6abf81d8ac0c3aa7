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
"""

from __future__ import annotations

import numpy as np

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
    F = np.einsum("tai,taJ->tiJ", X, G)  # (T, 3, 2)
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
    hpsi = (2.0 * mat.c20) * np.einsum("ti,tj->tij", g1, g1) + (2.0 * mat.c02) * np.einsum("ti,tj->tij", g2, g2) \
        + mat.c11 * (np.einsum("ti,tj->tij", g1, g2) + np.einsum("ti,tj->tij", g2, g1)) \
        + psi1[:, None, None] * h1 + psi2[:, None, None] * h2
    Dc2 = Dc.reshape(len(tris), 3, 9)
    Ke = np.einsum("tmA,tmn,tnB->tAB", Dc2, hpsi, Dc2)
    S = (2.0 * gpsi[:, 0, None, None] * Ga0[:, :, None] * Ga0[:, None, :]
         + 2.0 * gpsi[:, 1, None, None] * Ga1[:, :, None] * Ga1[:, None, :]
         + gpsi[:, 2, None, None] * (Ga0[:, :, None] * Ga1[:, None, :] + Ga1[:, :, None] * Ga0[:, None, :]))
    Ke = Ke.reshape(len(tris), 3, 3, 3, 3)  # (t, a, i, b, k)
    Ke += S[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    Ke = Ke.reshape(len(tris), 9, 9) * w[:, None, None]
    return fe, Ke, energy
