"""The meshing retries of ``build_model``: tumour-volume refinement and the rounded rim.

Synthetic: the half-ellipsoid phantom of ``test_model_synthetic`` (1 mm voxels) with a
small tumour; a failure is injected into one stage (a surface problem, a tumour surface
that loses volume) to check that the retry that follows is the formulation's, the same
for every exam.  Real: Pelicano exam 41, left breast (Pelicano et al., Sensors 2021 /
PLoS One 2024), whose outer surface failed every setting before the rounded rim.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_data
from regtrack.model import build as build_mod
from regtrack.model.build import attempt_plan, build_model, refine_tumour_factors, tumour_misses
from regtrack.model.config import MeshConfig
from regtrack.model.labels import PRESETS
from test_model_synthetic import SIMPLE, phantom


def _small_tumour_phantom(radius: float = 4.0):
    d = phantom(tumour=False)
    i, j, k = np.mgrid[0:120, 0:80, 0:120]
    d.data[(i - 60) ** 2 + (j - 40) ** 2 + (k - 60) ** 2 <= radius**2] = -3
    return d


def _t(err: float, ml: float = 0.1) -> dict:
    return {"volume_error": err, "voxel_volume_mm3": 1000.0 * ml}


@pytest.mark.parametrize(("tumours", "factors", "expect"), [
    ([_t(0.05), _t(-0.12)], [1.0, 1.0], [1.0, 0.7]),  # only the missing one is refined
    ([_t(0.15), _t(-0.12)], [0.7, 1.0], [0.49, 0.7]),
    ([_t(0.05), _t(0.0)], [1.0, 1.0], None),  # nothing misses
    ([_t(-0.2)], [0.7**3], None),  # at the floor tumour_refine_factor ** tumour_refinements
])
def test_refine_tumour_factors_table(tumours, factors, expect):
    out = refine_tumour_factors(tumours, factors, MeshConfig())
    if expect is None:
        assert out is None
    else:
        assert out == pytest.approx(expect)


def test_tumour_misses_honours_the_size_threshold():
    tum = [_t(-0.2, ml=0.05), _t(-0.2, ml=2.0)]
    assert tumour_misses(tum, MeshConfig()) == [0, 1]  # every kept tumour by default
    assert tumour_misses(tum, MeshConfig(check_tumour_min_ml=1.0)) == [1]


def test_attempt_plan_retries_do_not_depend_on_the_exam():
    plan = attempt_plan(MeshConfig())
    assert len(plan) == MeshConfig().max_attempts == 5
    assert [p["rim_fraction"] for p in plan] == [0.0, 0.0, 0.5, 0.5, 0.5]
    assert plan[1]["algorithm"] != plan[0]["algorithm"]
    assert plan[3]["smoothing_mm"] > plan[0]["smoothing_mm"] and plan[4]["size_factor"] < 1.0


def test_tumour_losing_volume_is_refined_until_within_tolerance(monkeypatch):
    """Inject a tumour surface 15 % short in volume whenever the tumour's element size is
    above 0.9 of its first size (a coarse surface that cuts the tumour): the first mesh
    fails the tumour check, one refinement round (sizes x 0.7) meets it, and the result
    meets every target of issue 3."""
    real = build_mod.make_surfaces
    first: list[float] = []

    def coarse_loses_volume(prep, *, tumour_edges_mm, **kw):
        res = real(prep, tumour_edges_mm=tumour_edges_mm, **kw)
        first.extend([] if first else tumour_edges_mm)
        if tumour_edges_mm[0] > 0.9 * first[0]:
            s = res.tumours[0]
            c = s.verts.mean(axis=0)
            s.verts = c + (s.verts - c) * 0.85 ** (1.0 / 3.0)
        return res

    monkeypatch.setattr(build_mod, "make_surfaces", coarse_loses_volume)
    m = build_model(_small_tumour_phantom(), scheme=SIMPLE, config=MeshConfig(target_nodes=2000))
    att = m.meta["attempts"]
    assert att[0]["tumour_refinement"] == 0
    assert att[0]["figures"]["tumours"][0]["volume_error"] == pytest.approx(-0.15, abs=0.02)
    assert att[0]["failed_checks"] == [att[0]["failed_checks"][0]] and "tumour 1" in att[0]["failed_checks"][0]
    assert att[-1]["attempt"] == 1 and att[-1]["tumour_refinement"] == 1  # same attempt, refined
    assert att[-1]["tumour_sizes_mm"][0] == pytest.approx(0.7 * att[0]["tumour_sizes_mm"][0])
    assert att[-1]["tumour_smoothing_mm"][0] == pytest.approx(0.7 * MeshConfig().tumour_smoothing_mm)
    q = m.meta["quality"]
    assert abs(q["tumours"][0]["volume_error"]) < 0.01  # the level set encloses the voxel volume
    assert q["n_inverted"] == 0 and q["min_dihedral_deg"] > 5.0 and q["gamma_p5"] > 0.3


def test_surface_failure_retries_with_a_rounded_rim(monkeypatch):
    """Every sharp-rim surface fails (as on exam 41 left): attempts 1 and 2 fail, the third
    (rim rounded over half an element) meshes and meets the targets."""
    real = build_mod.make_surfaces

    def sharp_rim_folds(prep, *, rim_mm=0.0, **kw):
        res = real(prep, rim_mm=rim_mm, **kw)
        if rim_mm == 0.0:
            res.problems = ["outer surface: 3 intersecting triangles (injected)"]
        return res

    monkeypatch.setattr(build_mod, "make_surfaces", sharp_rim_folds)
    m = build_model(_small_tumour_phantom(), scheme=SIMPLE, config=MeshConfig(target_nodes=2000))
    att = m.meta["attempts"]
    assert [a.get("error", "").startswith("surface checks failed") for a in att[:2]] == [True, True]
    assert att[-1]["attempt"] == 3 and att[-1]["rim_fraction"] == 0.5 and not att[-1]["failed_checks"]
    q = m.meta["quality"]
    assert abs(q["volume_error"]) < 0.03 and q["min_dihedral_deg"] > 5.0 and q["gamma_p5"] > 0.3
    assert m.fixed.sum() > 50  # the chest-wall cut face is still there


@pytest.mark.slow
@pytest.mark.realdata
def test_exam41_left_needs_the_rounded_rim():
    """Pelicano exam 41, left breast: its lateral skin meets the tilted chest-wall plane (16.7
    deg) in a wedge a few degrees thin; the sharp rim's remeshed triangles fold onto the cut
    face (22 intersecting, smallest angle 0.0 deg, every remeshing try and smoothing: ``regtrack
    mesh`` exit 2).  Rounded over half an element, the surfaces pass every check."""
    from regtrack.imaging.readers import read_label_map
    from regtrack.model.boundary import make_surfaces
    from regtrack.model.geometry import target_size
    from regtrack.model.prepare import prepare_breast

    cfg = MeshConfig()
    labels = read_label_map(shared_data("pelicano", "Exam_41", "Label_map_simple.zip"))
    prep = prepare_breast(labels, scheme=PRESETS["pelicano-simple"], config=cfg, side="L")
    h = target_size(prep.info["breast_voxel_volume_mm3"], cfg)
    kw = dict(edge_mm=h, tumour_edges_mm=[], smoothing_mm=cfg.smoothing_mm, tumour_smoothing_mm=0.8,
              clearance_mm=1.0, feature_fraction=cfg.feature_fraction, small_angle_deg=cfg.min_triangle_angle_deg)
    prep.tumours.kept = []  # the outer surface alone fails
    sharp = make_surfaces(prep, tries=1, **kw)
    assert any("intersecting" in p for p in sharp.problems)
    rounded = make_surfaces(prep, tries=1, rim_mm=cfg.retry_rim_fraction * h, **kw)
    assert not rounded.problems
    # the rounding shaves the thin rim only: volume within 1 % of the voxel volume
    assert rounded.outer.volume == pytest.approx(prep.info["breast_voxel_volume_mm3"], rel=0.01)


def test_failed_resizing_keeps_the_mesh_that_passed(monkeypatch):
    """A first mesh that passes every check but misses the node target by more than
    ``node_tolerance`` is re-sized; when the re-sized mesh fails a check (injected here, as
    exam 02 left did at 5.3 mm: min dihedral 0.4 deg), the first mesh is kept instead of
    spending every other attempt on the node count."""
    real_size, real_eval = build_mod.target_size, build_mod.evaluate
    calls = []

    def evaluate_second_fails(*a, **kw):
        fig, fail = real_eval(*a, **kw)
        calls.append(fig["n_nodes"])
        return fig, fail + (["min dihedral 0.40 deg < 5.0 (injected)"] if len(calls) == 2 else [])

    monkeypatch.setattr(build_mod, "target_size", lambda v, c: 0.75 * real_size(v, c))  # ~2.4x the nodes
    monkeypatch.setattr(build_mod, "evaluate", evaluate_second_fails)
    m = build_model(_small_tumour_phantom(), scheme=SIMPLE, config=MeshConfig(target_nodes=1000))
    assert len(calls) == 2 and calls[0] > 1.35 * 1000  # re-sized once
    assert m.n_nodes == calls[0] and len(m.meta["attempts"]) == 2
    assert not m.meta["attempts"][0]["failed_checks"]
