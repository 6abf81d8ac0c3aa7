"""The comparison with a compressed MRI on known offsets (issue 55, item 4).

A sphere of radius R sampled at 2,000 points against a voxelised sphere of radius R + d
(0.5 mm voxels, a flipped grid direction): every point lies d from the imaged surface, so
the RMS, mean, 95th percentile and maximum are d.  Tolerance 0.25 mm, half a voxel, for
the RMS, mean and 95th percentile: the marching-cubes surface of a binary mask is a
staircase within about half a voxel of the true one; the maximum within half the voxel's
diagonal (0.43 mm, measured 0.27 mm at d = 0).
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.errors import TrackingError
from regtrack.imaging.volume import LabelVolume, make_affine
from regtrack.tracking.compare import (imaged_surface, landmark_distances, surface_distance)
from regtrack.tracking.landmarks import Landmarks

CENTRE = np.array([-30.0, 12.0, 40.0])  # LPS mm


def _sphere_points(r, n=2000):
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5 ** 0.5) * k
    return CENTRE + r * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi),
                                  np.cos(phi)], axis=1)


def _ball(r):
    h, n = 0.5, 100
    direction = np.diag([-1.0, -1.0, 1.0])
    origin = CENTRE - direction @ np.full(3, h * (n - 1) / 2)
    affine = make_affine(origin, (h, h, h), direction)
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = ijk @ affine[:3, :3].T + affine[:3, 3]
    data = (np.linalg.norm(x - CENTRE, axis=1) <= r).astype(np.int16).reshape(n, n, n)
    return LabelVolume(data=data, affine=affine)


@pytest.mark.parametrize("offset", [0.0, 3.0, -2.0])
def test_surface_distance_of_a_known_offset(offset):
    R = 15.0
    labels = _ball(R + offset)
    surf = imaged_surface(labels, labels.data > 0)
    sd = surface_distance(_sphere_points(R), surf)
    d = abs(offset)
    for v in (sd.rms_mm, sd.mean_mm, sd.p95_mm):
        assert v == pytest.approx(d, abs=0.25)
    assert sd.max_mm <= d + 0.5 * np.sqrt(3) * 0.5 and sd.n_points == 2000


def test_empty_compressed_label_map_is_refused():
    labels = _ball(5.0)
    with pytest.raises(TrackingError, match="holds no breast voxel"):
        imaged_surface(labels, np.zeros(labels.data.shape, bool))


def test_landmark_distances_match_by_name():
    obs = Landmarks(("a", "b"), np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    rows = landmark_distances(["b", "a"], np.array([[1.0, 1.0, 4.0], [3.0, 4.0, 0.0]]), obs)
    assert [r["distance_mm"] for r in rows] == [3.0, 5.0]
    with pytest.raises(TrackingError, match=r"landmark 'c' is not in the compressed MRI"):
        landmark_distances(["c"], np.zeros((1, 3)), obs)


@pytest.mark.slow
def test_comparison_recovers_a_known_stiffness_mismatch():
    """A synthetic compressed MRI: the phantom's biopsy compression (26 %) simulated with
    nu = 0.40 (simulation B; bulk over shear modulus 4.7 instead of 50 at the default
    nu = 0.49, simulation A), its mesh voxelised by the project's warp (a constant tissue
    label map warped through B: the breast voxels are exactly B's deformed mesh).  The
    distance of A's skin to that image must recover the true distance of A's skin to B's
    deformed surface (sampled densely on B's boundary triangles): RMS within 0.3 mm, about
    half the 0.66 x 0.66 x 1.4 mm voxel (measured: 0.82 mm from the image, 0.94 mm
    true); B against its own image gives the resolution floor, below 0.5 mm (measured
    0.28 mm).

    Both are the pipeline's biopsy simulation of the case as bundled (its mesh, its
    composition c1; B with the nu override), taken from the stage cache shared with
    ``test_track_compressed``, whose tracking simulates A: without gravity, under a
    prescribed plate travel, c1 barely changes the shape, so the mismatch is nu's."""
    from regtrack.imaging.readers import read_label_map
    from regtrack.mechanics.meshes import boundary_faces
    from regtrack.tracking.compare import skin_distance
    from regtrack.tracking.compressed import open_compressed
    from regtrack.tracking.deformation import DeformationMap
    from regtrack.tracking.warp import warp_volume
    from tests.conftest import PIPELINE_CACHE, SAMPLE_CASES

    x, model, case = {}, None, None
    for name, nu in (("A", None), ("B", 0.40)):
        state = open_compressed(SAMPLE_CASES / "phantom01", "biopsy", cache_dir=PIPELINE_CACHE,
                                overrides=None if nu is None else {"mechanics": {"nu": nu}})
        assert state.summary["complete"]
        model, case = state.model, state.case
        x[name] = state.dmap.deformed
    assert case.config("mechanics").nu == 0.49  # the default: A is the stiffer bulk
    labels = read_label_map(case.mri.labels)
    tissue = case.mri.scheme.tissue[0]
    const = LabelVolume(data=np.full(labels.data.shape, tissue, labels.data.dtype),
                        affine=labels.affine)
    image_b = warp_volume(const, DeformationMap.from_model(model, x["B"])).volume
    floor = skin_distance(model, x["B"], image_b, case.mri.scheme)
    measured = skin_distance(model, x["A"], image_b, case.mri.scheme)
    F = boundary_faces(model.points, model.tets)
    w = np.random.default_rng(0).dirichlet([1, 1, 1], size=30)
    samples = np.vstack([np.einsum("sk,fkd->fsd", w, x["B"][F]).reshape(-1, 3),
                         x["B"][np.unique(F)]])
    skin = np.unique(model.skin)
    truth = surface_distance(model.frame.to_patient(x["A"][skin]),
                             model.frame.to_patient(samples))
    assert floor.rms_mm < 0.5
    assert truth.rms_mm > 2 * floor.rms_mm  # the mismatch is above the resolution floor
    assert measured.rms_mm == pytest.approx(truth.rms_mm, abs=0.3)
