"""Skin self-overlap (regtrack.mechanics.overlap): known-answer geometry."""

import numpy as np
import pytest

from regtrack.mechanics.meshes import boundary_faces
from regtrack.mechanics.overlap import closest_on_triangle, overlaps


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
    o = overlaps(P, T, F, np.zeros_like(P))
    d, n = o.depth, len(o.nodes)
    assert n == 8
    assert d == pytest.approx(depth, rel=1e-12)


def test_displacement_moves_the_cubes_apart_and_together():
    """Apart (a 0.5 mm gap) nothing overlaps; the displacement that sinks B 1.5 mm into A
    gives the overlap of the sunk geometry."""
    P, T, F = _two_cubes(0.5)
    assert len(overlaps(P, T, F, np.zeros_like(P)).nodes) == 0
    u = np.zeros_like(P)
    u[len(P) // 2:, 2] = -2.0
    o = overlaps(P, T, F, u)
    d, n = o.depth, len(o.nodes)
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
    q, _ = closest_on_triangle(p, np.tile(a, (k, 1)), np.tile(b, (k, 1)), np.tile(c, (k, 1)))
    got = np.linalg.norm(p - q, axis=1)
    assert got == pytest.approx(want, rel=1e-12)


def test_a_tip_through_a_face_is_one_overlap_at_its_depth_above_the_closest_point():
    """A tetrahedron pokes its apex 0.7 mm through the cube's top face, inside one of its
    triangles: the only overlapping node, 0.7 mm deep, its closest point straight above it
    on that face with barycentric weights summing to one."""
    PA, TA = _cube((0, 0, 0))
    PB = np.array([[2.0, 1.0, 11.0], [4.0, 1.0, 11.0], [3.0, 3.0, 11.0], [3.0, 2.0, 9.3]])
    TB = np.array([[0, 2, 1, 3]]) + len(PA)
    P, T = np.vstack([PA, PB]), np.vstack([TA, TB])
    o = overlaps(P, T, boundary_faces(P, T), np.zeros_like(P))
    assert list(o.nodes) == [len(PA) + 3]
    assert o.d[0] == pytest.approx(0.7, rel=1e-12)
    assert o.q[0] == pytest.approx([3.0, 2.0, 10.0], abs=1e-12)
    assert o.w[0].sum() == pytest.approx(1.0) and (o.w[0] > 0).all()
    assert np.allclose(o.w[0] @ P[o.tri[0]], o.q[0], atol=1e-12)
