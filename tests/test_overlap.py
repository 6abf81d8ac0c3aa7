"""Skin self-overlap (regtrack.mechanics.overlap): known-answer geometry."""

import numpy as np
import scipy.sparse as sp
import pytest

from regtrack.mechanics.contact import tributary_areas
from regtrack.mechanics.meshes import boundary_faces
from regtrack.mechanics.overlap import SkinContact, point_triangle_distance, skin_overlap


def _cube(origin, size=10.0, n=3):
    """A cube of ``(n-1)^3`` cells, six tetrahedra each (Kuhn split): points, tets."""
    g = np.linspace(0.0, size, n)
    P = np.array([[x, y, z] for x in g for y in g for z in g]) + np.asarray(origin, float)

    def idx(i, j, k):
        return (i * n + j) * n + k

    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    tets = []
    for i in range(n - 1):
        for j in range(n - 1):
            for k in range(n - 1):
                c = [idx(i + (b >> 2 & 1), j + (b >> 1 & 1), k + (b & 1)) for b in range(8)]
                tets += [[c[a] for a in t] for t in kuhn]
    T = np.array(tets)
    v = np.einsum("ij,ij->i", np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]),
                  P[T[:, 3]] - P[T[:, 0]])
    T[v < 0] = T[v < 0][:, [0, 2, 1, 3]]
    return P, T


def _two_cubes(lift):
    """Cube A = [0, 10]^3 and cube B shifted by (2.5, 2.5, 10 + lift): B's bottom face
    ``lift`` mm above A's top (inside A when negative), as one two-part mesh."""
    PA, TA = _cube((0, 0, 0))
    PB, TB = _cube((2.5, 2.5, 10.0 + lift))
    P = np.vstack([PA, PB])
    T = np.vstack([TA, TB + len(PA)])
    return P, T, boundary_faces(P, T)


@pytest.mark.parametrize("depth", [0.5, 1.5])
def test_two_overlapping_cubes_give_the_depth_and_the_nodes(depth):
    """B sunk ``depth`` mm into A (spacing 5 mm): A's top nodes (5|10, 5|10, 10) are inside
    B and B's bottom nodes (2.5|7.5, 2.5|7.5) inside A, eight in all, each ``depth`` from
    the other cube's face (the side faces are at least 2.5 mm away)."""
    P, T, F = _two_cubes(-depth)
    d, n = skin_overlap(P, T, np.zeros_like(P), F)
    assert n == 8
    assert d == pytest.approx(depth, rel=1e-12)


def test_displacement_moves_the_cubes_apart_and_together():
    """Apart (a 0.5 mm gap) nothing overlaps; the displacement that sinks B 1.5 mm into A
    gives the overlap of the sunk geometry."""
    P, T, F = _two_cubes(0.5)
    assert skin_overlap(P, T, np.zeros_like(P), F) == (0.0, 0)
    u = np.zeros_like(P)
    u[len(P) // 2:, 2] = -2.0
    d, n = skin_overlap(P, T, u, F)
    assert (n, d) == (8, pytest.approx(1.5, rel=1e-12))


def test_point_triangle_distance_in_each_voronoi_region():
    """Above the interior, beyond each edge and beyond each corner of the triangle
    (0,0,0), (4,0,0), (0,4,0): the distances in closed form."""
    a, b, c = np.array([0.0, 0, 0]), np.array([4.0, 0, 0]), np.array([0.0, 4, 0])
    p = np.array([[1.0, 1, 3],      # interior: 3
                  [2.0, -2, 0],     # beyond ab: 2
                  [-3.0, 2, 4],     # beyond ac: 5
                  [3.0, 3, 0],      # beyond bc: |(3,3)-(2,2)| = sqrt 2
                  [-1.0, -1, 1],    # corner a: sqrt 3
                  [6.0, -1, 0],     # corner b: sqrt 5
                  [-2.0, 7, 0]])    # corner c: sqrt 13
    want = [3.0, 2.0, 5.0, np.sqrt(2), np.sqrt(3), np.sqrt(5), np.sqrt(13)]
    k = len(p)
    got = point_triangle_distance(p, np.tile(a, (k, 1)), np.tile(b, (k, 1)), np.tile(c, (k, 1)))
    assert got == pytest.approx(want, rel=1e-12)


def _sunk(depth, eps=0.02):
    P, T, F = _two_cubes(-depth)
    return P, T, F, SkinContact(P, T, F, penalty=eps)


def test_the_penalty_energy_is_half_eps_area_depth_squared_over_the_overlapping_nodes():
    """Sunk 1.5 mm: the eight overlapping nodes, each 1.5 mm deep, give ``1/2 eps sum A_i
    d^2`` with their tributary areas, and the forces are internal (they sum to zero)."""
    eps, depth = 0.02, 1.5
    P, T, F, sc = _sunk(depth, eps)
    ev = sc.evaluate(np.zeros_like(P), hessian=True)
    assert len(ev.overlaps.nodes) == 8
    want = 0.5 * eps * float(np.sum(tributary_areas(P, F)[ev.overlaps.nodes])) * depth ** 2
    assert ev.energy == pytest.approx(want, rel=1e-12)
    assert np.abs(ev.grad.reshape(-1, 3).sum(axis=0)).max() < 1e-12


def test_the_penalty_gradient_is_the_derivative_of_its_energy():
    """Central differences of ``Pi_S`` along a random displacement of every node match
    ``grad . v`` (the closest points move with the triangles; h = 1e-6 mm, the energy is
    piecewise smooth away from a change of the crossed triangle)."""
    P, T, F, sc = _sunk(1.2)
    rng = np.random.default_rng(3)
    u = 0.05 * rng.standard_normal(P.shape)
    v = rng.standard_normal(P.shape)
    h = 1e-6
    g = sc.evaluate(u, hessian=False).grad
    fd = (sc.evaluate(u + h * v, hessian=False).energy - sc.evaluate(u - h * v, hessian=False).energy) / (2 * h)
    assert g @ v.reshape(-1) == pytest.approx(fd, rel=1e-6)


def test_the_penalty_hessian_blocks_are_the_gauss_newton_diagonal():
    """The node's block is ``eps A n n^T`` (n: out of the tissue, here +z or -z): positive
    semi-definite with the one eigenvalue ``eps A`` along ``n``."""
    eps = 0.02
    P, T, F, sc = _sunk(1.5, eps)
    ev = sc.evaluate(np.zeros_like(P), hessian=True)
    rows, cols, vals = ev.hess
    H = np.zeros((P.size, P.size))
    np.add.at(H, (rows, cols), vals)
    i = int(ev.overlaps.nodes[0])
    block = H[3 * i:3 * i + 3, 3 * i:3 * i + 3]
    A = tributary_areas(P, F)[i]
    ez = np.diag([0.0, 0.0, 1.0])
    assert block[2, 2] >= eps * A * (1 - 1e-12)  # its own share, and maybe a triangle's
    assert np.linalg.eigvalsh(H).min() > -1e-12
    assert np.allclose(block - block[2, 2] * ez, 0.0, atol=1e-15)


def test_the_gauss_newton_node_block_is_the_derivative_of_the_node_force():
    """A tetrahedron pokes its apex 0.7 mm into the cube's top face, inside one of its
    triangles: the only overlap, whose ``d^2`` is the squared distance to that flat
    triangle's plane, so the Gauss-Newton block ``eps A n n^T`` (n = -z) is exact and
    matches central differences of the apex's gradient (h = 1e-6 mm)."""
    PA, TA = _cube((0, 0, 0))
    PB = np.array([[2.0, 1.0, 11.0], [4.0, 1.0, 11.0], [3.0, 3.0, 11.0], [3.0, 2.0, 9.3]])
    TB = np.array([[0, 2, 1, 3]]) + len(PA)
    P, T = np.vstack([PA, PB]), np.vstack([TA, TB])
    p = P[TB[0]]
    assert np.linalg.det(np.stack([p[1] - p[0], p[2] - p[0], p[3] - p[0]], 1)) > 0
    eps = 0.02
    sc = SkinContact(P, T, boundary_faces(P, T), penalty=eps)
    u = np.zeros_like(P)
    ev = sc.evaluate(u, hessian=True)
    apex = len(PA) + 3
    assert list(ev.overlaps.nodes) == [apex] and ev.overlaps.d[0] == pytest.approx(0.7, rel=1e-12)
    rows, cols, vals = ev.hess
    H = sp.coo_matrix((vals, (rows, cols)), shape=(P.size, P.size)).toarray()
    i = 3 * apex
    A = tributary_areas(P, boundary_faces(P, T))[apex]
    assert H[i:i + 3, i:i + 3] == pytest.approx(np.diag([0.0, 0.0, eps * A]), abs=1e-15)
    h = 1e-6
    fd = np.zeros((3, 3))
    for k in range(3):
        du = np.zeros_like(P)
        du[apex, k] = h
        fd[:, k] = (sc.evaluate(u + du, hessian=False).grad[i:i + 3]
                    - sc.evaluate(u - du, hessian=False).grad[i:i + 3]) / (2 * h)
    # central differences of a 0.03 N gradient at h = 1e-6 carry ~1e-11 N/mm of round-off
    assert np.allclose(H[i:i + 3, i:i + 3], fd, rtol=1e-6, atol=1e-9)
