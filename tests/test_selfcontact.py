"""The outer surface's self-contact barrier (regtrack.mechanics.selfcontact): known answers.

Why the tolerances:

* the barrier's derivatives: central differences (h = 1e-6 mm) of a smooth function of
  order-1 values, to 1e-6 relative (truncation O(h^2), round-off 1e-16 / h);
* the potential's gradient: central differences of ``Pi_S`` along random directions (h =
  1e-6 mm) to 1e-6 relative; the distance is C1 across the triangle's Voronoi regions, so
  the directional derivative is exact away from measure-zero switches;
* the distance's Hessian and a pair's Hessian: central differences (h = 1e-6 mm) of the
  exact gradient, within one Voronoi region of the triangle (the probes are 0.3 mm or more
  from a region's border), to 1e-7 absolute on entries of order 0.05-1 (1/mm) and 1e-6
  relative on the pair's Hessian (round-off 1e-16 / h on gradients of order 1);
* two equal boxes pressed together between clamped faces: by mirror symmetry the bonded
  stack has no shear on its mid-plane, so a frictionless contact there carries the force of
  the bonded 8 mm box compressed by the same amount less the contact gap; 3 % covers the
  node-to-face barrier's uneven pressure and the Kuhn mesh, which is not mirror symmetric
  (1.6 % measured).
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import ConfigError
from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.contact import ContactConfig, tributary_areas
from regtrack.mechanics.meshes import boundary_faces, box_model
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.overlap import closest_on_triangle, overlaps
from regtrack.mechanics.placement import BodySetup, skin_barrier
from regtrack.mechanics.problem import build_problem
from regtrack.mechanics.selfcontact import CCD_SAFETY, SkinBarrier, barrier, distance_hessian
from regtrack.model.types import BreastModel

DHAT = 0.5


def _stack(gap: float) -> tuple[BreastModel, int]:
    """Box A = [0, 10]^2 x [0, 4] (its bottom clamped) and box B, the same box ``gap`` mm
    above it, as one two-part model; returns the model and A's node count."""
    A = box_model((10.0, 10.0, 4.0), (4, 4, 3))
    B = box_model((10.0, 10.0, 4.0), (4, 4, 3), origin=(0.0, 0.0, 4.0 + gap))
    P = np.vstack([A.points, B.points])
    T = np.vstack([A.tets, B.tets + len(A.points)])
    fixed = np.zeros(len(P), bool)
    fixed[: len(A.points)] = np.isclose(A.points[:, 2], 0.0)
    model = BreastModel(points=P, tets=T, region=np.ones(len(T), int), tumour_id=np.zeros(len(T), int),
                        skin=boundary_faces(P, T), fixed=fixed, nipple=0, frame=A.frame)
    return model, len(A.points)


def _barrier(model: BreastModel, kappa: float = 0.02) -> SkinBarrier:
    X = model.points
    F = boundary_faces(X, np.asarray(model.tets)[:, :4])
    return SkinBarrier(X, F, tributary_areas(X, F), kappa=kappa, dhat=DHAT)


def test_the_barrier_and_its_derivatives():
    d = np.linspace(0.01, 0.7, 60) * DHAT
    b, b1, b2 = barrier(d, DHAT)
    h = 1e-6
    assert np.allclose(b1, (barrier(d + h, DHAT)[0] - barrier(d - h, DHAT)[0]) / (2 * h), rtol=1e-6, atol=1e-9)
    assert np.allclose(b2, (barrier(d + h, DHAT)[1] - barrier(d - h, DHAT)[1]) / (2 * h), rtol=1e-6, atol=1e-9)
    assert np.all(b > 0) and np.all(b1 < 0) and np.all(b2 > 0)  # repulsive and convex
    # C2 at the reach, zero beyond, unbounded at contact
    at = barrier(np.array([DHAT, 2 * DHAT]), DHAT)
    assert all(np.all(v == 0.0) for v in at)
    near = barrier(np.array([1e-3, 1e-12]), DHAT)[0]  # ~ dhat^2 ln(dhat / d)
    assert near[1] > 4 * near[0]


def test_the_gradient_is_that_of_the_potential_and_the_hessian_is_psd():
    model, _ = _stack(0.3)
    bar = _barrier(model)
    rng = np.random.default_rng(3)
    u = 0.05 * rng.standard_normal(model.points.shape)
    e = bar.evaluate(u, hessian=True)
    assert e.n_active > 20 and 0 < e.d_min < DHAT
    pairs, _ = bar.near(u, 0.02 * np.ones_like(u))  # every pair the probes can reach
    h = 1e-6
    for _ in range(5):
        v = rng.standard_normal(u.shape)
        fd = (bar.evaluate(u + h * v, pairs).energy - bar.evaluate(u - h * v, pairs).energy) / (2 * h)
        assert fd == pytest.approx(float(e.grad @ v.reshape(-1)), rel=1e-6)
    rows, cols, vals = e.hess
    keep = np.unique(np.concatenate([rows, cols]))
    idx = np.searchsorted(keep, rows), np.searchsorted(keep, cols)
    H = np.zeros((len(keep), len(keep)))
    np.add.at(H, idx, vals)
    w = np.linalg.eigvalsh(H)
    assert np.allclose(H, H.T) and w.min() >= -1e-10 * w.max()


#: a triangle and points above its face, beside each edge and beyond each corner
_TRIANGLE = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [2.0, 8.0, 0.0]])
_PROBES = {"face": (3.0, 2.0, 0.3), "edge 0-1": (5.0, -1.5, 0.3), "edge 1-2": (7.0, 5.0, 0.2),
           "edge 2-0": (-0.8, 4.0, 0.4), "corner 0": (-1.0, -1.0, 0.3),
           "corner 1": (11.0, -0.5, 0.2), "corner 2": (2.0, 9.0, 0.3)}


def _distance_gradient(y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """dd/dy (12,) of the point-triangle distance at ``y`` = (point, 3 corners), with the
    weights and ``r`` of the closest point."""
    p, c = y[:3], y[3:].reshape(3, 3)
    q, w = closest_on_triangle(p[None], c[None, 0], c[None, 1], c[None, 2])
    r = p - q[0]
    n = r / np.linalg.norm(r)
    return np.concatenate([n, *(-w[0, k] * n for k in range(3))]), w[0], r


@pytest.mark.parametrize("region", list(_PROBES))
def test_the_distance_hessian_is_that_of_the_distance(region):
    """``distance_hessian`` against central differences of the exact gradient, in every
    Voronoi region of a triangle turned at random in space."""
    rng = np.random.default_rng(len(region))
    R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    y = np.concatenate([np.array(_PROBES[region]) @ R.T, (_TRIANGLE @ R.T).ravel()])
    _, w, r = _distance_gradient(y)
    H = distance_hessian(r[None], w[None], y[3:].reshape(1, 3, 3))[0]
    h = 1e-6
    fd = np.stack([(_distance_gradient(y + h * e)[0] - _distance_gradient(y - h * e)[0]) / (2 * h)
                   for e in np.eye(12)], axis=1)
    assert np.abs(fd).max() > 0.05
    assert np.allclose(H, fd, rtol=0.0, atol=1e-7)


def test_the_distance_hessian_of_a_crushed_triangle_is_finite():
    """A triangle crushed to a segment (its corners on a line) has no face region; the
    point's distance to it is that to the segment, whose Hessian is finite."""
    corners = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]])
    H = distance_hessian(np.array([[0.0, 0.0, 0.3]]), np.array([[0.3, 0.4, 0.3]]), corners)
    assert np.all(np.isfinite(H)) and np.allclose(H, np.swapaxes(H, 1, 2))


#: points within the barrier's reach of ``_TRIANGLE``: above the face, beside an edge, beyond a corner
_NEAR = {"face": (3.0, 2.0, 0.3), "edge 1-2": (6.15, 4.15, 0.2), "corner 0": (-0.2, -0.25, 0.2)}


@pytest.mark.parametrize("region", list(_NEAR))
def test_a_pairs_hessian_is_its_whole_hessian_projected(region):
    """One node within reach of one triangle (its own triangle turned away): the barrier's
    Hessian is the finite-difference Hessian of its energy with the negative eigenvalues
    clamped, including the distance's own curvature (``b' d^2d``), not only ``b'' g g^T``."""
    T = _TRIANGLE
    p = np.array(_NEAR[region])
    out = p[:2] - T[:, :2].mean(axis=0)
    a = np.append(out / np.linalg.norm(out), 1.0)             # up and away from the triangle
    b = np.array([-a[1], a[0], 0.0])
    X = np.vstack([T, p, p + 6.0 * a + 3.0 * b, p + 6.0 * a - 3.0 * b])
    F = np.array([[0, 1, 2], [3, 4, 5]])
    bar = SkinBarrier(X, F, np.ones(len(X)), kappa=0.02, dhat=DHAT)
    u = np.zeros_like(X)
    e = bar.evaluate(u, hessian=True)
    # beyond a corner, the node and that corner are each other's nearest (the same term twice)
    assert e.n_active == (2 if region.startswith("corner") else 1)
    pairs, _ = bar.near(u, 0.01 * np.ones_like(u))
    h = 1e-6
    fd = np.stack([(bar.evaluate(u + h * v.reshape(-1, 3), pairs).grad
                    - bar.evaluate(u - h * v.reshape(-1, 3), pairs).grad) / (2 * h)
                   for v in np.eye(u.size)], axis=1)
    lam, V = np.linalg.eigh(0.5 * (fd + fd.T))
    want = V @ np.diag(np.maximum(lam, 0.0)) @ V.T
    rows, cols, vals = e.hess
    H = np.zeros_like(fd)
    np.add.at(H, (rows, cols), vals)
    assert np.allclose(H, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
    # the Gauss-Newton part alone (rank one, along the gradient) misses the distance's
    # curvature along a triangle turning under the node; beyond a corner that curvature is
    # negative (the distance to a point is convex, b' < 0) and the projection removes it
    g = e.grad / np.linalg.norm(e.grad)
    rank_one = np.allclose(H, np.outer(g, g) * (g @ H @ g), rtol=1e-3, atol=1e-3 * np.abs(want).max())
    assert rank_one == region.startswith("corner")


def test_no_step_crosses_a_triangle():
    """A node 1 mm above the middle of a box's top face, moved 3 mm straight down (through
    the face): the allowed step keeps it ``(1 - 0.9) 0.4`` mm above; with its box sliding
    along the face, or moved together with both boxes, it may take the whole step."""
    model, nA = _stack(0.6)
    bar = _barrier(model)
    X = model.points
    i = nA + int(np.argmin(np.linalg.norm(X[nA:] - [5.0, 5.0, 4.6], axis=1)))  # B's bottom centre
    u = np.zeros_like(X)
    u[i, 2] = 0.4 - 0.6  # 0.4 mm above A
    du = np.zeros_like(X)
    du[i, 2] = -3.0
    _, alpha = bar.near(u, du)
    assert alpha == pytest.approx(CCD_SAFETY * 0.4 / 3.0, rel=1e-9)
    # B sliding 1 mm along A's top keeps the distance: the whole step (the additive CCD
    # strides along; a single conservative bound would allow 0.36)
    du[:] = 0.0
    du[nA:] = (1.0, 0.0, 0.0)
    assert bar.near(u, du)[1] == 1.0
    # everything translates by 1 mm: nothing closes
    du[:] = (0.0, 0.0, -1.0)
    assert bar.near(u, du)[1] == 1.0
    assert bar.near(u)[1] == 1.0
    # a step too long to search within the budget (B lifted 30 mm off A) is bounded to
    # the part searched, 2^-k
    du[:] = 0.0
    du[nA:] = (0.0, 0.0, 30.0)
    a = bar.near(u, du)[1]
    assert 0 < a < 1 and np.log2(a) == np.round(np.log2(a))


def _smooth_field(X: np.ndarray, rng, amplitude: float) -> np.ndarray:
    """A smooth random displacement field (N, 3) mm: sines of wavelength 10-30 mm."""
    k = rng.uniform(0.2, 0.6, (3, 3)) * rng.choice([-1.0, 1.0], (3, 3))
    return amplitude * np.sin(X @ k + rng.uniform(0.0, 2 * np.pi, 3))


def test_the_neighbour_list_finds_what_a_tree_search_finds():
    """Box B sliding along A's top (0.4 mm a step, 4.8 mm in all: two elements) under a
    smooth random wobble (so the list is re-made on the way): the pairs within reach, the
    pairs of a step and its bound from the neighbour list are those of a tree search at
    every state; a pair only the search returns is one the bound proves cannot come within
    reach in the step."""
    model, nA = _stack(0.6)
    X = model.points
    bar, ref = _barrier(model), _barrier(model)
    ref._listed = lambda *args: None  # type: ignore[method-assign]  # always search
    rng = np.random.default_rng(7)
    u = np.zeros_like(X)
    lists, within = set(), 0
    for _ in range(12):
        du = _smooth_field(X, rng, 0.1)
        du[nA:, 0] += 0.4
        got, want = bar.near(u, margin=2.0)[0], ref.near(u, margin=2.0)[0]
        lists.add(id(bar._list[0]))
        assert set(zip(got.node, got.tri)) == set(zip(want.node, want.tri))
        within += len(got)
        (got, a), (want, b) = bar.near(u, du), ref.near(u, du)
        assert a == b
        g, w = set(zip(got.node, got.tri)), set(zip(want.node, want.tri))
        assert g <= w
        extra = np.array(sorted(w - g), np.int64).reshape(-1, 2)
        for t in np.linspace(0.0, 1.0, 11):
            gap = bar._gap(X + u, du, np.full(len(extra), t), extra[:, 0], extra[:, 1])
            assert np.all(np.linalg.norm(gap, axis=1) >= DHAT)
        u = u + du
    assert within > 0 and len(lists) >= 2  # pairs were found, and the list was re-made


def test_the_system_matrix_holds_the_barriers_couplings():
    """``Minimiser.matrix`` with pairs in reach: the mesh's matrix plus the barrier's
    Hessian between free dofs (summed independently with scipy; equal to rounding), and
    at a later state with fewer pairs (B tilted off A) the same pattern (the union of the
    pairs coupled so far, zeros where a pair is out of reach) with that state's values."""
    import scipy.sparse as sp

    from regtrack.mechanics.newton import Minimiser

    model, nA = _stack(0.6)
    prob = build_problem(model, MechanicsConfig(tissue_c1_kpa=1.0, nu=0.45))
    prob.self_contact = _barrier(model)
    m = Minimiser(prob, prob.config.solver)
    fext = np.zeros(prob.n_dofs)
    u = np.zeros_like(model.points)
    matrices = []
    for tilt in (0.0, 0.1):  # B 0.25 mm above A, then tilted up to 1.25 mm at its far end
        u[nA:, 2] = -0.35 + tilt * model.points[nA:, 0]
        s = m.state(u, fext, [], hessian=True)
        M = m.matrix(s, s.ev, 0.0)
        rows, cols, vals = s.skin.hess
        keep = m.free[rows] & m.free[cols]
        H = sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=M.shape)
        plain = Minimiser(prob, prob.config.solver)
        plain.barrier = None
        s0 = plain.state(u, fext, [], hessian=True)
        want = (plain.matrix(s0, s0.ev, 0.0) + H).toarray()
        assert np.allclose(M.toarray(), want, rtol=0, atol=1e-12 * np.abs(want).max())
        matrices.append((M, s.skin.n_active))
    (first, n_first), (later, n_later) = matrices
    assert n_first > n_later > 0 and later.nnz == first.nnz
    assert np.array_equal(later.indices, first.indices) and np.array_equal(later.indptr, first.indptr)


@pytest.mark.parametrize("with_barrier", [True, False])
def test_two_boxes_pressed_together_carry_the_force_of_one(with_barrier):
    """B's top face is pushed 1 mm down onto A (0.6 mm below it) with A's bottom clamped.
    With the barrier, B rests on A: no node of either enters the other, the gap ends
    within the barrier's reach, the force through the stack balances, and it equals the
    bonded 8 mm box's at the same compression (module docstring).  Without it B sinks 0.4 mm
    into A and carries nothing."""
    model, nA = _stack(0.6)
    prob = build_problem(model, MechanicsConfig(tissue_c1_kpa=1.0, nu=0.45))
    prob.self_contact = _barrier(model) if with_barrier else None
    X = model.points
    top = np.flatnonzero(np.isclose(X[:, 2], 8.6))
    dofs = (3 * top[:, None] + np.arange(3)).reshape(-1)

    def push(t, delta=1.0):
        v = np.zeros((len(top), 3))
        v[:, 2] = -t * delta
        return dofs, v.reshape(-1)

    u, _, R = minimise_step(prob, np.zeros_like(X), dirichlet=push, n_increments=4)
    F = boundary_faces(X, np.asarray(model.tets)[:, :4])
    inside = overlaps(X, model.tets, F, u)
    force_top = -R[top, 2].sum()
    if not with_barrier:
        assert inside.depth == pytest.approx(0.4, abs=1e-6) and abs(force_top) < 1e-9
        return
    assert len(inside.nodes) == 0
    x = X + u
    gap = x[nA:][np.isclose(X[nA:, 2], 4.6), 2] - x[:nA][np.isclose(X[:nA, 2], 4.0), 2]
    assert np.all((gap > 0) & (gap < DHAT))
    assert R[model.fixed, 2].sum() == pytest.approx(force_top, rel=1e-6)
    C = box_model((10.0, 10.0, 8.0), (4, 4, 6))
    C.fixed[:] = np.isclose(C.points[:, 2], 0.0)
    topc = np.flatnonzero(np.isclose(C.points[:, 2], 8.0))
    dc = (3 * topc[:, None] + np.arange(3)).reshape(-1)
    squeeze = 1.0 - (0.6 - gap.mean())

    def press(t):
        v = np.zeros((len(topc), 3))
        v[:, 2] = -t * squeeze
        return dc, v.reshape(-1)

    pc = build_problem(C, MechanicsConfig(tissue_c1_kpa=1.0, nu=0.45))
    _, _, Rc = minimise_step(pc, np.zeros_like(C.points), dirichlet=press, n_increments=4)
    assert force_top == pytest.approx(-Rc[topc, 2].sum(), rel=0.03)


def test_a_reach_wider_than_the_reference_gap_is_halved_to_it():
    """Two boxes 0.3 mm apart: a 0.5 mm reach (the default) would load the reference, so
    the barrier reaches half the gap; a reach under the gap is kept; 0 turns it off; boxes
    that touch are refused (the surface meets itself: not a valid solid)."""
    model, _ = _stack(0.3)

    def body(m):
        return BodySetup(points=m.points, tets=m.tets, surface=m.skin, fixed=m.fixed,
                         side="R", young_mpa=0.003)

    assert ContactConfig().self_contact_gap_mm == 0.5
    assert skin_barrier(body(model), ContactConfig()).dhat == pytest.approx(0.15, rel=1e-9)
    assert skin_barrier(body(model), ContactConfig(self_contact_gap_mm=0.25)).dhat == 0.25
    assert skin_barrier(body(model), ContactConfig(self_contact_gap_mm=0.0)) is None
    touching, _ = _stack(0.0)
    with pytest.raises(ConfigError, match=r"self_contact_gap_mm: the model's outer surface "
                                          r"touches itself"):
        skin_barrier(body(touching), ContactConfig())
