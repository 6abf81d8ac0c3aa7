"""Skin membrane (incompressible plane-stress polynomial model) vs analytic Cauchy stress.

Reference: for principal stretches (l1, l2) and l3 = 1/(l1 l2),
sigma_i = 2 (li^2 - l3^2) Psi_1 - 2 (li^-2 - l3^-2) Psi_2 (sigma_3 = 0), evaluated
independently of the implementation's invariant-chain derivation.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.materials import skin_material
from regtrack.mechanics.membrane import membrane_forces, reference_geometry

MAT = skin_material(MechanicsConfig())


def analytic_sigma(l1, l2, m=MAT):
    l3 = 1.0 / (l1 * l2)
    I1 = l1**2 + l2**2 + l3**2
    I2 = (l1 * l2) ** 2 + (l2 * l3) ** 2 + (l1 * l3) ** 2
    a, b = I1 - 3, I2 - 3
    p1 = m.c10 + m.c11 * b + 2 * m.c20 * a
    p2 = m.c01 + m.c11 * a + 2 * m.c02 * b
    s = [2 * (li**2 - l3**2) * p1 - 2 * (li**-2 - l3**-2) * p2 for li in (l1, l2)]
    return np.array(s), l3


def patch(n=3, size=(10.0, 6.0)):
    """Tilted square patch (so the test is not aligned with the axes), n x n quads -> triangles."""
    xs, ys = np.linspace(0, size[0], n + 1), np.linspace(0, size[1], n + 1)
    P2 = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    idx = np.arange(len(P2)).reshape(n + 1, n + 1)
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            tris += [[a, b, c], [a, c, d]]
    return P2, np.array(tris)


def edge_force(l1, l2, *, rot):
    P2, tris = patch()
    e1, e2 = rot[:, 0], rot[:, 1]
    X = P2[:, :1] * e1 + P2[:, 1:] * e2
    x = (l1 * P2[:, :1]) * e1 + (l2 * P2[:, 1:]) * e2
    G, A0 = reference_geometry(X, tris)
    fe, _, _ = membrane_forces(x, tris, G, A0, MAT, want_k=False)
    f = np.zeros_like(X)
    for a in range(3):
        np.add.at(f, tris[:, a], fe[:, a])
    right = np.abs(P2[:, 0] - 10.0) < 1e-9
    top = np.abs(P2[:, 1] - 6.0) < 1e-9
    return f[right].sum(0) @ e1, f[top].sum(0) @ e2, np.abs(f[~(right | top | (P2[:, 0] < 1e-9) | (P2[:, 1] < 1e-9))]).max(initial=0)


ROT = np.linalg.qr(np.array([[1.0, 0.3, 0.2], [0.2, 1.0, -0.4], [0.1, 0.5, 1.0]]))[0]


@pytest.mark.parametrize("lam", [1.05, 1.3, 1.8])
def test_equibiaxial_cauchy_stress(lam):
    # 1 %: the acceptance bound; the homogeneous state is exact for linear triangles,
    # so the observed error is round-off.
    fx, fy, interior = edge_force(lam, lam, rot=ROT)
    sig, l3 = analytic_sigma(lam, lam)
    H = MAT.thickness
    # edge force = sigma * current thickness (H l3) * current edge length
    assert fx == pytest.approx(sig[0] * H * l3 * lam * 6.0, rel=1e-2)
    assert fy == pytest.approx(sig[1] * H * l3 * lam * 10.0, rel=1e-2)
    assert interior < 1e-12 * abs(fx)


@pytest.mark.parametrize("lam", [1.1, 1.5, 2.0])
def test_uniaxial_cauchy_stress(lam):
    l2 = brentq(lambda l2: analytic_sigma(lam, l2)[0][1], 0.3, 1.0)
    fx, fy, _ = edge_force(lam, l2, rot=ROT)
    sig, l3 = analytic_sigma(lam, l2)
    assert fx == pytest.approx(sig[0] * MAT.thickness * l3 * l2 * 6.0, rel=1e-2)
    assert abs(fy) < 1e-6 * abs(fx)  # the lateral edge is traction free at the analytic l2


def test_membrane_tangent_finite_difference():
    P2, tris = patch(2)
    X = np.c_[P2, np.zeros(len(P2))] @ ROT.T
    rng = np.random.default_rng(3)
    x = X + 0.4 * rng.standard_normal(X.shape)
    assert_consistent(X, x, tris, rng)


def assert_consistent(X, x, tris, rng, mat=MAT):
    """Central differences along a random direction: the tangent is the derivative of the
    forces (relative error < 1e-6) and the forces are the gradient of the energy."""
    G, A0 = reference_geometry(X, tris)
    fe, Ke, _ = membrane_forces(x, tris, G, A0, mat, want_k=True)
    d = rng.standard_normal(x.shape)
    h = 1e-6
    fp, _, ep = membrane_forces(x + h * d, tris, G, A0, mat, want_k=False)
    fm, _, em = membrane_forces(x - h * d, tris, G, A0, mat, want_k=False)
    fd = ((fp - fm) / (2 * h)).reshape(len(tris), 9)
    an = np.einsum("tab,tb->ta", Ke, d[tris].reshape(len(tris), 9))
    assert np.linalg.norm(fd - an) / np.linalg.norm(an) < 1e-6
    assert (ep - em) / (2 * h) == pytest.approx(np.sum(fe * d[tris]), rel=1e-6)


# -- wrinkling (tension-field theory) ------------------------------------------------------

PLAIN = skin_material(MechanicsConfig(skin_wrinkling=False))


@pytest.mark.parametrize("lam", [1.1, 1.5])
@pytest.mark.parametrize("l2", [0.5, 0.8])
def test_wrinkled_membrane_carries_the_uniaxial_tension(lam, l2):
    # laterally squeezed below its natural width, the membrane wrinkles: its force is that
    # of the uniaxial state at the same l1 (the natural width l2* from the closed form) and
    # the lateral edge carries nothing; round-off bound 1e-6 (the states are homogeneous)
    assert MAT.wrinkling
    l2n = brentq(lambda s: analytic_sigma(lam, s)[0][1], 0.3, 1.0)
    assert l2 < l2n
    fx, fy, _ = edge_force(lam, l2, rot=ROT)
    sig, l3 = analytic_sigma(lam, l2n)
    assert fx == pytest.approx(sig[0] * MAT.thickness * l3 * l2n * 6.0, rel=1e-6)
    assert abs(fy) < 1e-9 * abs(fx)


def test_slack_membrane_carries_nothing_and_the_plain_one_compression():
    P2, tris = patch()
    X = np.c_[P2, np.zeros(len(P2))] @ ROT.T
    x = np.c_[0.9 * P2[:, :1], 0.8 * P2[:, 1:], np.zeros(len(P2))] @ ROT.T
    G, A0 = reference_geometry(X, tris)
    fe, Ke, e = membrane_forces(x, tris, G, A0, MAT, want_k=True)
    assert e == 0.0 and not fe.any() and not Ke.any()
    fe, _, e = membrane_forces(x, tris, G, A0, PLAIN, want_k=False)
    assert e > 0 and np.abs(fe).max() > 0  # the plain polynomial energy resists compression


@pytest.mark.parametrize("theta", [0.0, 0.4, 1.2])
def test_wrinkled_tangent_finite_difference(theta):
    # wrinkle direction rotated by theta in the plane: the tangent carries the rotation of
    # the principal direction (Hessian of the eigenvalue); relative error < 1e-6 as above
    P2, tris = patch(2)
    X = np.c_[P2, np.zeros(len(P2))] @ ROT.T
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s], [s, c]])
    U = R @ np.diag([1.3, 0.7]) @ R.T
    rng = np.random.default_rng(5)
    x = np.c_[P2 @ U.T, np.zeros(len(P2))] @ ROT.T + 0.01 * rng.standard_normal(X.shape)
    G, A0 = reference_geometry(X, tris)
    e = membrane_forces(x, tris, G, A0, MAT, want_k=False)[2]
    assert e < membrane_forces(x, tris, G, A0, PLAIN, want_k=False)[2]  # relaxed: wrinkled
    assert_consistent(X, x, tris, rng)


def test_forces_do_not_depend_on_the_tangent_request():
    """The kernels that form the forces alone and with the tangent give the same bits
    (the line search compares residuals from both), wrinkled and taut triangles alike."""
    rng = np.random.default_rng(11)
    P2, tris = patch(6)
    X = np.c_[P2, np.zeros(len(P2))] @ ROT.T
    S = P2 * rng.uniform(0.6, 1.4, P2.shape)  # some triangles stretched, some wrinkled or slack
    x = np.c_[S, 0.3 * rng.standard_normal(len(P2))] @ ROT.T
    G, A0 = reference_geometry(X, tris)
    fk, Ke, ek = membrane_forces(x, tris, G, A0, MAT, want_k=True)
    f, K0, e = membrane_forces(x, tris, G, A0, MAT, want_k=False)
    assert K0 is None and ek == e
    assert np.array_equal(fk, f)
    c = np.einsum("tiJ,tiK->tJK", *(2 * [np.einsum("tai,taJ->tiJ", x[tris], G)]))
    mu1 = 0.5 * (c[:, 0, 0] + c[:, 1, 1] + np.hypot(c[:, 0, 0] - c[:, 1, 1], 2 * c[:, 0, 1]))
    mu2 = np.linalg.det(c) / mu1
    assert (mu2 < 0.8).any() and (mu1 > 1.2).any()  # the states span wrinkling and tension
    np.testing.assert_allclose(Ke, Ke.transpose(0, 2, 1), rtol=0, atol=1e-12 * np.abs(Ke).max())


def test_corner_forces_sum_like_add_at():
    """problem._add_corner_forces accumulates in np.add.at's order: the same bits."""
    from regtrack.mechanics.problem import _add_corner_forces

    rng = np.random.default_rng(3)
    cells, fe = rng.integers(0, 50, size=(400, 3)), rng.normal(size=(400, 3, 3))
    f1 = rng.normal(size=(50, 3))
    f2 = f1.copy()
    for a in range(3):
        np.add.at(f1, cells[:, a], fe[:, a])
    _add_corner_forces(f2, cells, fe)
    assert np.array_equal(f1, f2)
