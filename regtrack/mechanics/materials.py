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
    """

    c1: np.ndarray
    kappa: np.ndarray
    rho: np.ndarray
    group: np.ndarray


@dataclass(frozen=True)
class SkinMaterial:
    """Skin membrane constants (MPa) and reference thickness (mm)."""

    c10: float
    c01: float
    c11: float
    c20: float
    c02: float
    thickness: float


def element_materials(region: np.ndarray, config: MechanicsConfig) -> ElementMaterials:
    """Material data per tetrahedron from ``region`` (1 tissue, 2 tumour) and ``config``."""
    region = np.asarray(region)
    tum = region == TUMOUR
    nu_t = config.nu if config.tumour_nu is None else config.tumour_nu
    c1 = np.where(tum, config.tumour_c1_kpa, config.tissue_c1_kpa) * KPA
    nu = np.where(tum, nu_t, config.nu)
    kappa = bulk_modulus(2.0 * c1, nu)
    rho = np.full(len(region), float(config.density_kg_m3))
    return ElementMaterials(c1=c1, kappa=kappa, rho=rho, group=tum.astype(np.int64))


def skin_material(config: MechanicsConfig) -> SkinMaterial:
    """Skin membrane constants from ``config`` (Pa -> MPa)."""
    return SkinMaterial(
        c10=config.skin_c10_pa * PA, c01=config.skin_c01_pa * PA, c11=config.skin_c11_pa * PA,
        c20=config.skin_c20_pa * PA, c02=config.skin_c02_pa * PA, thickness=config.skin_thickness_mm,
    )
