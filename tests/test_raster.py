"""Known answers of the triangle rasteriser (:mod:`regtrack.virtual.raster`): the owner
rule gives every pixel centre of a tiling to exactly one triangle, also when the centres
lie on the triangles' shared edges and vertices."""

import numpy as np
from scipy.spatial import ConvexHull, Delaunay

from regtrack.virtual.raster import Grid, rasterise


def _lattice_tiling(n: int, m: int):
    """Vertices on the pixel centres of an (m + 1) x (n + 1) lattice, two triangles a cell,
    the diagonals alternating (every edge and vertex of the tiling on pixel centres)."""
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(m + 1.0))
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    idx = np.arange(pts.shape[0]).reshape(m + 1, n + 1)
    tris = []
    for r in range(m):
        for c in range(n):
            a, b, d, e = idx[r, c], idx[r, c + 1], idx[r + 1, c], idx[r + 1, c + 1]
            tris += [[a, b, e], [a, e, d]] if (r + c) % 2 else [[a, b, d], [b, e, d]]
    return pts, np.array(tris)


def test_a_tiling_on_pixel_centres_covers_each_inner_centre_once():
    """A 10 x 8 rectangle tiled with vertices on pixel centres: each of the 9 x 7 inner
    centres once, none twice; the constant 1 interpolates to 1 (the barycentric weights sum
    to the triangle's area); an outer grid margin stays empty."""
    pts, tris = _lattice_tiling(10, 8)
    grid = Grid((-2.0, -2.0), 1.0, (13, 15))
    count, acc = rasterise(pts, tris, grid, values=np.ones(len(pts)))
    assert count.max() == 1
    inner = count[3:10, 3:12]  # rows y = 1..7, columns x = 1..9
    assert inner.shape == (7, 9) and inner.min() == 1
    np.testing.assert_allclose(acc[count == 1], 1.0, atol=1e-12)
    assert count[:2].sum() == count[-2:].sum() == count[:, :2].sum() == count[:, -2:].sum() == 0


def test_random_triangulation_counts_every_inside_centre_once():
    """A Delaunay triangulation of random points (some on pixel centres): every centre
    strictly inside the convex hull (by more than 1e-9 mm) counted exactly once, every one
    strictly outside not at all, and a linear field reproduced inside (1e-9)."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 20, (400, 2))
    pts[:60] = np.round(pts[:60] * 4) / 4  # on the centres of the 0.25 mm grid
    tri = Delaunay(pts)
    grid = Grid((-1.0, -1.0), 0.25, (89, 89))
    values = 2.0 * pts[:, 0] - 3.0 * pts[:, 1] + 1.0
    count, acc = rasterise(pts, tri.simplices, grid, values=values)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    q = np.stack([X.ravel(), Y.ravel()], 1)
    eq = ConvexHull(pts).equations  # n . x + d <= 0 inside
    side = (q @ eq[:, :2].T + eq[:, 2]).max(axis=1)
    c = count.ravel()
    assert c.max() == 1
    assert np.all(c[side < -1e-9] == 1) and np.all(c[side > 1e-9] == 0)
    inside = c == 1
    np.testing.assert_allclose(acc.ravel()[inside], 2.0 * q[inside, 0] - 3.0 * q[inside, 1] + 1.0,
                               atol=1e-9)
