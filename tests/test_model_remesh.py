"""Known-answer tests of the surface stage of ``regtrack.model`` (remeshing and checks).

Analytic shapes on 1-mm grids: a sphere (volume, angles, closedness), a cut sphere (flat
cut face), overlapping and nested spheres (intersection test), a slab with a thin crevice
(closing/opening), and a tumour straddling a cut plane (cut and uncut voxel volumes).
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.model.boundary import open_close, smooth_min, surface_step
from regtrack.model.chestwall import Plane
from regtrack.model.prepare import uncut_volumes
from regtrack.model.remesh import (check_surfaces, intersecting_faces, open_edges, remesh, restore_volume,
                                   snap_to_planes, triangle_angles)
from regtrack.model.surfaces import Surface, extract_surface
from regtrack.model.tumours import find_tumours

EYE = np.eye(4)


def sphere_field(n: int, r: float, centre=None) -> np.ndarray:
    c = np.full(3, (n - 1) / 2.0) if centre is None else np.asarray(centre, float)
    i, j, k = np.mgrid[0:n, 0:n, 0:n].astype(float)
    return r - np.sqrt((i - c[0]) ** 2 + (j - c[1]) ** 2 + (k - c[2]) ** 2)


def sphere(r: float = 15.0, n: int = 40, centre=None) -> Surface:
    return extract_surface(sphere_field(n, r, centre), EYE, relax_iterations=0)


def test_remeshed_sphere_is_closed_clean_and_keeps_its_volume():
    raw = sphere(15.0)
    assert open_edges(raw.faces) == 0
    out = remesh(raw, edge_mm=3.0)
    chk = check_surfaces([out], small_angle_deg=20.0)[0]
    assert chk.n_open_edges == 0 and chk.n_intersecting == 0
    # isotropic remeshing: no triangle angle below 20 deg (marching cubes has ~0 deg ones)
    assert triangle_angles(raw.verts, raw.faces).min() < 5.0
    assert chk.min_angle_deg > 20.0
    # edge lengths near the target (Botsch-Kobbelt keeps them within [4/5, 4/3] L)
    e = np.linalg.norm(out.verts[out.faces] - out.verts[out.faces[:, [1, 2, 0]]], axis=2).ravel()
    assert 2.4 < np.median(e) < 4.0
    # volume: the chords lose ~ L^2 / (4 R^2) ~ 1 %; restore_volume brings the surface back
    # to the analytic 4/3 pi r^3 within 0.3 % (the marching-cubes surface itself is within
    # 0.3 % of it on a 1-mm grid at r = 15 mm)
    exact = 4.0 / 3.0 * np.pi * 15.0**3
    assert raw.volume == pytest.approx(exact, rel=3e-3)
    fixed = restore_volume(out, raw.volume)
    assert fixed.volume == pytest.approx(raw.volume, rel=1e-3)
    r = np.linalg.norm(fixed.verts - 19.5, axis=1)
    assert np.abs(r - 15.0).max() < 0.3  # every vertex within 0.3 mm of the sphere


def test_cut_face_stays_planar_after_remeshing():
    # sphere r = 15 cut by the plane i = 19.5 + 5 (normal -i: the model is on the low side)
    g = sphere_field(40, 15.0)
    plane = Plane(np.array([-1.0, 0.0, 0.0]), -24.5, "chest_wall")
    i = np.arange(40, dtype=float)[:, None, None]
    g = np.minimum(g, np.broadcast_to(plane.normal[0] * i - plane.offset, g.shape))
    raw = extract_surface(g, EYE, step=1, relax_iterations=0)
    out = remesh(raw, edge_mm=3.0, planes=(plane,), snap_mm=0.5)
    d = plane.distance(out.verts)
    assert d.min() > -1e-9  # nothing beyond the plane
    on = np.abs(d) < 1e-9
    # cut disc of radius sqrt(15^2 - 5^2) = 14.1 mm: vertices on it at ~3 mm spacing
    assert on.sum() > 50
    assert np.linalg.norm(out.verts[on][:, 1:] - 19.5, axis=1).max() == pytest.approx(np.sqrt(200.0), abs=0.6)
    chk = check_surfaces([out], small_angle_deg=10.0, planes=(plane,))[0]
    assert chk.n_intersecting == 0 and chk.n_open_edges == 0 and chk.min_angle_deg > 10.0


def test_snap_leaves_a_skin_wedge_alone():
    # a triangle fan whose normals face away from the cut face is not flattened onto it
    plane = Plane(np.array([0.0, 0.0, 1.0]), 0.0, "chest_wall")
    v = np.array([[0, 0, 0.3], [1, 0, 0.3], [0, 1, 0.3]], float)
    f = np.array([[0, 1, 2]])  # normal +z: skin above the plane, facing out of the model
    assert np.allclose(snap_to_planes(v, f, (plane,), 0.5), v)
    f_cut = f[:, ::-1]  # normal -z: a cut-face triangle: projected onto the plane
    assert np.allclose(snap_to_planes(v, f_cut, (plane,), 0.5)[:, 2], 0.0)


def test_intersection_test_known_answers():
    a = remesh(sphere(8.0, 40, (15, 20, 20)), edge_mm=2.0)
    b_cross = remesh(sphere(8.0, 40, (25, 20, 20)), edge_mm=2.0)  # centres 10 mm apart < 16
    inner = remesh(sphere(4.0, 40, (15, 20, 20)), edge_mm=1.5)  # nested, 4 mm gap
    sa, sb = intersecting_faces([a, b_cross])
    assert sa.sum() > 0 and sb.sum() > 0
    sa, si = intersecting_faces([a, inner])
    assert sa.sum() == 0 and si.sum() == 0


def test_open_close_removes_a_thin_crevice_and_keeps_the_block():
    m = np.zeros((40, 40, 40), bool)
    m[5:35, 5:35, 5:35] = True
    m[18:20, 5:30, 10:30] = False  # a 2-voxel-wide crevice, 25 deep
    out = open_close(m, 2.0, np.ones(3))
    assert out[18:20, 6:30, 10:30].all()  # the crevice is filled (but its one-voxel mouth)
    blk = np.zeros_like(m)
    blk[5:35, 5:35, 5:35] = True
    # the block is kept except along its 12 edges, rounded by the opening (radius 2 mm):
    # only voxels within the r x r corner square of an edge may go
    assert (out & ~blk).sum() == 0
    assert 0 < (blk & ~out).sum() <= 12 * 30 * 2 * 2


def test_smooth_min_is_min_away_from_the_crease():
    a = np.array([0.0, 1.0, 5.0])
    b = np.array([0.0, 0.0, 0.0])
    s = smooth_min(a, b, 2.0)
    assert s[2] == 0.0 and s[0] == pytest.approx(-0.5) and s[1] < 0.0


def test_marching_cubes_with_step_closes_at_the_array_border():
    # regression (Pelicano exam 11): with step 2 and an odd padded size the last layer was
    # skipped, leaving the surface open where the body leaves the field of view
    g = np.ones((21, 20, 20))
    g[:, 0, :] = g[:, -1, :] = g[:, :, 0] = g[:, :, -1] = -1.0
    for step in (1, 2, 3):
        s = extract_surface(g, EYE, step=step, relax_iterations=0)
        assert open_edges(s.faces) == 0
        assert s.volume > 0


def test_surface_step_follows_the_edge_length():
    assert surface_step(5.0, np.ones(3)) == 2
    assert surface_step(1.0, np.ones(3)) == 1
    assert surface_step(10.0, np.ones(3), 4) == 4


def test_uncut_volume_of_a_tumour_straddling_the_cut():
    # 10x10x10 voxel cube, 4 layers of which lie beyond the cut (crop starts at index 4)
    full = np.zeros((20, 20, 20), bool)
    full[0:10, 5:15, 5:15] = True
    sl = (slice(4, 20), slice(0, 20), slice(0, 20))
    ts = find_tumours(full[sl], np.full(full[sl].shape, -3), voxel_volume=2.0, min_volume_mm3=1.0)
    assert ts.kept[0].volume_mm3 == pytest.approx(6 * 100 * 2.0)
    assert uncut_volumes(ts, full, sl, 2.0) == [pytest.approx(1000 * 2.0)]
