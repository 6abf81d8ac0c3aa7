r"""Material laws and per-element material data (internal units mm-N-MPa).

Tissue / tumour: nearly incompressible neo-Hookean (the peers' form, peers/README.md)

.. math:: W(F) = c_1 (J^{-2/3}\operatorname{tr} C - 3) + \tfrac{K}{2}(J-1)^2

with :math:`\mu = 2c_1` and :math:`K = 2\mu(1+\nu)/(3(1-2\nu))`, so that linearising at
:math:`F = I` gives isotropic elasticity with shear modulus :math:`\mu`, Young's modulus
:math:`E = 2\mu(1+\nu)` and Poisson ratio :math:`\nu`.

Skin: incompressible plane-stress polynomial membrane
:math:`\Psi = \sum_{1\le i+j\le 2} c_{ij}(I_1-3)^i(I_2-3)^j` (see :mod:`.membrane`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regtrack.mechanics.config import MechanicsConfig
from regtrack.model.types import TUMOUR

KPA = 1e-3  # MPa per kPa
PA = 1e-6  # MPa per Pa
G_SCALE = 1e-9  # (kg/m^3) * (m/s^2) = N/m^3 -> N/mm^3


def bulk_modulus(mu: float | np.ndarray, nu: float | np.ndarray) -> np.ndarray:
    """``K = 2 mu (1 + nu) / (3 (1 - 2 nu))`` (same unit as ``mu``)."""
    mu = np.asarray(mu, float)
    nu = np.asarray(nu, float)
    return 2.0 * mu * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


def young_modulus(c1: float, nu: float) -> float:
    """Small-strain Young's modulus ``E = 2 mu (1 + nu) = 4 c1 (1 + nu)`` of the neo-Hookean W."""
    return 4.0 * c1 * (1.0 + nu)


@dataclass(frozen=True)
class ElementMaterials:
    """Per-tetrahedron material data, internal units.

    Attributes
    ----------
    c1 : (E,) float
        neo-Hookean c1 (MPa).
    kappa : (E,) float
        Bulk modulus K (MPa).
    rho : (E,) float
        Density (kg/m^3); the body force per reference volume is ``rho * g * 1e-9`` N/mm^3
        with ``g`` in m/s^2.
    group : (E,) int
        Material group index (0 tissue, 1 tumour); the average-nodal-pressure formulation
        averages the volume change per (node, group) so stiff inclusions do not smear.
    tissue_young_mpa : float
        Small-strain Young's modulus of the tissue's (volume-weighted mean) c1 (MPa): the
        scale of the automatic contact penalty.
    """

    c1: np.ndarray
    kappa: np.ndarray
    rho: np.ndarray
    group: np.ndarray
    tissue_young_mpa: float = 0.0


@dataclass(frozen=True)
class SkinMaterial:
    """Skin membrane constants (MPa) and reference thickness (mm)."""

    c10: float
    c01: float
    c11: float
    c20: float
    c02: float
    thickness: float
    wrinkling: bool = False  # tension-field (relaxed) energy: no compression, see .membrane


@dataclass(frozen=True)
class TissueStiffness:
    r"""c1 of the tissue elements under ``[mechanics] tissue_model``.

    Per element, from its MRI label ``l`` (``tissue_label`` of the model):

    .. math:: c_1(l) = \begin{cases} c_1^{gland} & l \in \text{gland\_labels} \\
              \tfrac12 (c_1^{fat} + c_1^{gland}) & l \in \text{transition\_labels} \\
              c_1^{fat} & \text{otherwise (fat, skin voxels)} \end{cases}

    ``composition`` gives every tissue element the volume-weighted (Voigt) mean
    :math:`\bar c_1 = \sum_e V_e c_1(l_e) / \sum_e V_e` over the tissue elements: still the
    paper's homogenised model, with its stiffness set by the patient's fat/gland make-up.
    (Voigt is the upper bound of the homogenised shear modulus; the lower, Reuss bound
    :math:`1 / \overline{(1/c_1)}` is reported beside it.)  ``heterogeneous`` keeps
    :math:`c_1(l_e)` per element, with the bulk modulus of the mean (``nu`` is the Poisson
    ratio of :math:`\bar c_1`), as the phantom's ground truth does.  ``homogeneous``:
    ``tissue_c1_kpa`` everywhere.

    Attributes
    ----------
    c1_kpa : (E,) float
        c1 of every element (tumour elements hold the tissue value; the caller replaces it).
    mean_kpa : float
        Volume-weighted mean c1 of the tissue elements (the bulk modulus and the contact
        penalty use it).
    info : dict
        Model, per-class c1, tissue volume fractions, Voigt and Reuss means (for reports).
    """

    c1_kpa: np.ndarray
    mean_kpa: float
    info: dict


def tissue_stiffness(region: np.ndarray, tissue_label: np.ndarray | None, volumes: np.ndarray,
                     config: MechanicsConfig, *, where: str = "[mechanics]") -> TissueStiffness:
    """c1 of the tissue elements (kPa), see :class:`TissueStiffness`.

    Raises :class:`~regtrack.errors.ConfigError` when a fat/gland model is asked of a model
    without MRI labels, or whose labels hold neither class.
    """
    from regtrack.errors import ConfigError

    region = np.asarray(region)
    ne = len(region)
    if config.tissue_model == "homogeneous":
        c1 = float(config.tissue_c1_kpa)
        return TissueStiffness(np.full(ne, c1), c1, {"model": "homogeneous", "c1_kpa": c1})
    fat, gland = float(config.fat_c1_kpa), float(config.gland_c1_kpa)
    if tissue_label is None:
        raise ConfigError(f"{where} tissue_model = '{config.tissue_model}' needs the MRI label of every "
                          "element, and this model has none (a model written before labels were kept, "
                          "or from a mesh file): re-mesh it from the label map, or use "
                          "tissue_model = 'homogeneous'")
    lab = np.asarray(tissue_label).reshape(-1)
    tissue = region != TUMOUR
    is_gland = np.isin(lab, config.gland_labels)
    is_trans = np.isin(lab, config.transition_labels)
    is_fat = np.isin(lab, config.fat_labels)
    if not (is_gland | is_fat)[tissue].any():
        found = sorted(int(v) for v in np.unique(lab[tissue]))[:12]
        raise ConfigError(f"{where} tissue_model = '{config.tissue_model}': no tissue element carries a "
                          f"fat_labels {list(config.fat_labels)} or gland_labels "
                          f"{list(config.gland_labels)} value (the model's tissue labels are {found}); "
                          "mesh a label map that separates fat and gland (scheme 'pelicano-detailed'), "
                          "set fat_labels / gland_labels to its values, or use tissue_model = 'homogeneous'")
    c1 = np.full(ne, fat)
    c1[is_gland] = gland
    c1[is_trans] = 0.5 * (fat + gland)
    v = np.abs(np.asarray(volumes, float))[tissue]
    vt = float(v.sum())
    voigt = float(np.sum(v * c1[tissue]) / vt)
    reuss = float(vt / np.sum(v / c1[tissue]))
    frac = {"gland": float(v[is_gland[tissue]].sum() / vt),
            "transition": float(v[is_trans[tissue]].sum() / vt),
            "fat": float(v[is_fat[tissue]].sum() / vt)}
    frac["other (fat c1)"] = max(0.0, 1.0 - sum(frac.values()))
    info = {"model": config.tissue_model, "fat_c1_kpa": fat, "gland_c1_kpa": gland,
            "transition_c1_kpa": 0.5 * (fat + gland), "tissue_volume_fraction": frac,
            "voigt_mean_c1_kpa": voigt, "reuss_mean_c1_kpa": reuss}
    if config.tissue_model == "composition":
        c1 = np.full(ne, voigt)
        info["c1_kpa"] = voigt
    return TissueStiffness(c1, voigt, info)


def element_materials(region: np.ndarray, config: MechanicsConfig,
                      tissue: TissueStiffness | None = None) -> ElementMaterials:
    """Material data per tetrahedron from ``region`` (1 tissue, 2 tumour) and ``config``.

    ``tissue`` (:func:`tissue_stiffness`) gives the tissue c1 per element; without it the
    tissue is homogeneous with ``tissue_c1_kpa``.  The tissue's bulk modulus is that of its
    volume-weighted mean c1 and ``nu``.  This is where the configuration's kPa become the
    MPa of the mechanics, once.
    """
    region = np.asarray(region)
    tum = region == TUMOUR
    nu_t = config.nu if config.tumour_nu is None else config.tumour_nu
    c1_t = tissue.c1_kpa if tissue is not None else np.full(len(region), config.tissue_c1_kpa)
    c1_mean = tissue.mean_kpa if tissue is not None else config.tissue_c1_kpa
    # kPa (the configuration) -> MPa (the mechanics): the one conversion
    c1_t, c1_mean, c1_tum = (np.asarray(v, float) * KPA for v in (c1_t, c1_mean, config.tumour_c1_kpa))
    c1 = np.where(tum, c1_tum, c1_t)
    nu = np.where(tum, nu_t, config.nu)
    kappa = bulk_modulus(2.0 * np.where(tum, c1_tum, c1_mean), nu)
    rho = np.full(len(region), float(config.density_kg_m3))
    return ElementMaterials(c1=c1, kappa=kappa, rho=rho, group=tum.astype(np.int64),
                            tissue_young_mpa=young_modulus(float(c1_mean), config.nu))


def skin_material(config: MechanicsConfig) -> SkinMaterial:
    """Skin membrane constants from ``config`` (Pa -> MPa)."""
    return SkinMaterial(
        c10=config.skin_c10_pa * PA, c01=config.skin_c01_pa * PA, c11=config.skin_c11_pa * PA,
        c20=config.skin_c20_pa * PA, c02=config.skin_c02_pa * PA, thickness=config.skin_thickness_mm,
        wrinkling=config.skin_wrinkling,
    )
