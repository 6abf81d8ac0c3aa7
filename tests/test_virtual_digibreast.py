"""X-ray-like line integrals on a real compressed-breast mesh.

Data: DigiBreast ``ForwardMesh`` (Deng B., Fang Q. et al., 2015; public domain): a
compressed breast of 14,490 nodes and 65,196 tets, compression along z (mm).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data

from regtrack.virtual import xray
from regtrack.virtual.contours import mask_contours, polygon_area
from regtrack.virtual.raster import grid_around, rasterise
from regtrack.virtual.surface import boundary_faces

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def forward_mesh():
    from scipy.io import loadmat

    d = loadmat(shared_data("digibreast", "DigiBreast.mat"), squeeze_me=True, struct_as_record=False)
    fm = d["ForwardMesh"]
    return np.asarray(fm.node, float), np.asarray(fm.elem, np.int64) - 1  # 1-based in the file


def test_line_integrals_of_real_mesh(forward_mesh):
    pts, tets = forward_mesh
    p = pts[tets]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]),
                           p[:, 3] - p[:, 0])).sum() / 6
    grid = grid_around(pts[:, :2], spacing=0.5, margin=2)
    length = xray.path_lengths(pts, tets, np.ones(len(tets), int), grid)[1]
    # divergence theorem: the path-length image integrates to the mesh volume; the
    # pixel-centre rule on a 0.5 mm grid errs by much less than 0.1 % (measured 0.04 %)
    assert length.sum() * grid.pixel_area == pytest.approx(vol, rel=1e-3)
    # the compressed breast spans the full plate gap somewhere: max path = z extent
    assert length.max() == pytest.approx(np.ptp(pts[:, 2]), abs=0.05)
    assert length.min() >= 0.0
    # one outline whose polygon area matches the pixel count (within half a pixel of the edge)
    mask = rasterise(pts[:, :2], boundary_faces(tets, pts), grid)[0] > 0
    (outline,) = mask_contours(mask, grid)
    perimeter = np.linalg.norm(np.diff(np.vstack([outline, outline[:1]]), axis=0), axis=1).sum()
    assert abs(polygon_area(outline) - mask.sum() * grid.pixel_area) < 0.5 * grid.spacing * perimeter
    assert np.all(length[~mask] == 0.0)
