"""Fat/gland tissue stiffness (``[mechanics] tissue_model``): label mapping, the homogenised
(Voigt) mean, and two-layer bars against the closed-form bounds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from regtrack.errors import ConfigError
from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.materials import KPA, bulk_modulus, tissue_stiffness
from regtrack.mechanics.meshes import box_model
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.problem import build_problem, reaction_forces
from regtrack.model.types import TUMOUR
from tests.test_mechanics_analytic import roller_dirichlet

L = 10.0
FAT, GLAND = 1.0, 3.0  # kPa


def layered_box(axis: int, divisions=(4, 4, 4)):
    """Box whose half ``x_axis < L/2`` is gland (label 2), the rest fat (label 6)."""
    m = box_model((L, L, L), divisions)
    cen = m.points[m.tets].mean(axis=1)
    return dataclasses.replace(m, tissue_label=np.where(cen[:, axis] < L / 2, 2, 6))


def cfg(model="heterogeneous", **kw):
    return MechanicsConfig(tissue_model=model, fat_c1_kpa=FAT, gland_c1_kpa=GLAND, skin_enabled=False, **kw)


def test_labels_map_to_classes_and_composition_is_the_volume_mean():
    m = box_model((L, L, L), (2, 2, 2))
    lab = np.array([2, 6, 4, -2] * (m.n_tets // 4))  # gland, fat, transition, skin voxel
    region = np.ones(m.n_tets, int)
    region[0] = TUMOUR
    vol = np.full(m.n_tets, 2.0)
    vol[1] = 6.0  # a bigger fat element
    het = tissue_stiffness(region, lab, vol, cfg())
    expect = np.select([lab == 2, lab == 4], [GLAND, 0.5 * (FAT + GLAND)], FAT)
    np.testing.assert_array_equal(het.c1_kpa[1:], expect[1:])
    t = region != TUMOUR
    voigt = np.sum(vol[t] * expect[t]) / vol[t].sum()
    reuss = vol[t].sum() / np.sum(vol[t] / expect[t])
    assert het.mean_kpa == pytest.approx(voigt, rel=1e-12)
    assert het.info["reuss_mean_c1_kpa"] == pytest.approx(reuss, rel=1e-12)
    assert sum(het.info["tissue_volume_fraction"].values()) == pytest.approx(1.0)
    comp = tissue_stiffness(region, lab, vol, cfg("composition"))
    np.testing.assert_allclose(comp.c1_kpa, voigt, rtol=1e-12)
    assert comp.info["c1_kpa"] == pytest.approx(voigt)
    homo = tissue_stiffness(region, lab, vol, MechanicsConfig(tissue_c1_kpa=0.7))
    np.testing.assert_array_equal(homo.c1_kpa, 0.7)


def test_problem_materials_follow_the_tissue_model():
    m = layered_box(0)
    pr = build_problem(m, cfg())
    gland = m.tissue_label == 2
    np.testing.assert_allclose(pr.mats.c1[gland], GLAND * KPA)
    np.testing.assert_allclose(pr.mats.c1[~gland], FAT * KPA)
    # one bulk modulus, that of the mean c1 with nu (the ANP pressure is shared)
    np.testing.assert_allclose(pr.mats.kappa, bulk_modulus(2 * 0.5 * (FAT + GLAND) * KPA, 0.49))
    assert pr.tissue_c1.info["model"] == "heterogeneous"


@pytest.mark.parametrize("nu", [0.3, 0.49])
def test_two_layer_bars_against_voigt_and_reuss(nu):
    """0.5 % uniaxial compression (small strain) of a half-gland, half-fat cube.

    Layers side by side (parallel to the load) share the axial strain: the force is the
    Voigt mean of the layers' Young's moduli (measured 0.09 to 0.28 % above it; the layers'
    different lateral contraction couples them slightly; bound 1 %).  Layers stacked along
    the load are bounded by Reuss (series, free lateral faces) below and Voigt above; they
    sit 7 to 12 % above Reuss because the interface forces a common lateral strain.
    """
    K = bulk_modulus(2 * 0.5 * (FAT + GLAND) * KPA, nu)
    E = [9 * K * mu / (3 * K + mu) for mu in (2 * FAT * KPA, 2 * GLAND * KPA)]
    eps = 0.005
    voigt = 0.5 * (E[0] + E[1]) * eps * L * L
    reuss = eps * L * L / (0.5 / E[0] + 0.5 / E[1])
    force = {}
    for axis in (0, 2):
        pr = build_problem(layered_box(axis), cfg(nu=nu))
        dirichlet, top = roller_dirichlet(pr.X, -eps * L)
        u, _, _ = minimise_step(pr, np.zeros_like(pr.X), dirichlet=dirichlet, n_increments=4, step_name="bar")
        force[axis] = -reaction_forces(pr, u)[top, 2].sum()
    assert force[0] == pytest.approx(voigt, rel=1e-2)
    assert reuss < force[2] < voigt
    assert force[2] > 1.03 * reuss  # the lateral coupling is there (the test can fail)


def test_fat_gland_model_needs_labels_and_stiffnesses():
    m = box_model((L, L, L), (2, 2, 2))
    with pytest.raises(ConfigError, match="re-mesh it from the label map"):
        build_problem(m, cfg())
    with pytest.raises(ConfigError, match="separates fat and gland"):
        build_problem(dataclasses.replace(m, tissue_label=np.ones(m.n_tets, int) * 9), cfg())
    from regtrack.config import parse_section

    _, problems, _ = parse_section(MechanicsConfig, {"tissue_model": "composition"}, where="case.toml [mechanics]")
    assert any("needs fat_c1_kpa and gland_c1_kpa" in p for p in problems)


def test_phantom_truth_material_map():
    """The phantom generator's per-element c1 (regtrack.phantom.truth_sim, which uses the
    heterogeneous map on the phantom's own label constants): gland 1-3, transition 4 (the
    mean), fat 5-7 and skin voxels, tumour; and its volume mean equals the map's."""
    from regtrack.phantom.mammo_params import MammoTruthParams
    from regtrack.phantom.truth_sim import element_c1_kpa, material_summary

    p = MammoTruthParams()
    m = box_model((L, L, L), (3, 3, 3))
    rng = np.random.default_rng(0)
    region = np.where(rng.random(m.n_tets) < 0.1, TUMOUR, 1)
    lab = rng.choice([-2, 1, 2, 3, 4, 5, 6, 7], m.n_tets)
    m = dataclasses.replace(m, region=region, tissue_label=lab)
    truth = element_c1_kpa(m, p)
    expect = np.select([region == TUMOUR, np.isin(lab, (1, 2, 3)), lab == 4],
                       [p.tumour_c1_kpa, p.gland_c1_kpa, 0.5 * (p.fat_c1_kpa + p.gland_c1_kpa)], p.fat_c1_kpa)
    np.testing.assert_array_equal(truth, expect)
    mine = tissue_stiffness(m.region, m.tissue_label, m.tet_volumes(),
                            MechanicsConfig(tissue_model="heterogeneous", fat_c1_kpa=p.fat_c1_kpa,
                                            gland_c1_kpa=p.gland_c1_kpa))
    assert mine.mean_kpa == pytest.approx(material_summary(m, truth, p)["tissue_c1_mean_kpa"], rel=1e-12)
