"""Parameters of the synthetic prone breast phantom."""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param, parse_section
from regtrack.errors import ConfigError


@dataclass(frozen=True)
class PhantomParams:
    """Seeded, parametric prone breast phantom (all lengths in mm).

    The breast mound is a sheared half super-ellipsoid on the chest wall (see
    :func:`regtrack.phantom.geometry.breast_mound`); the tumour an ellipsoid with a smooth
    random surface modulation.  The default tumour is the paper's 25 x 22 x 25 mm lesion
    (Lapuebla-Ferri et al.).  Voxel spacing defaults to the paper's scanner,
    0.66 x 0.66 x 1.4 mm, with axial slices (axis 0 = L, axis 1 = P, axis 2 = S).
    """

    seed: int = param(1, "-", "random seed of the texture and tumour shape", ge=0)
    side: str = param("R", "-", "breast side (patient's right or left)", choices=("R", "L"))
    base_width_mm: float = param(130.0, "mm", "medio-lateral diameter of the breast base", gt=20, le=300)
    base_height_mm: float = param(120.0, "mm", "cranio-caudal diameter of the breast base", gt=20, le=300)
    projection_mm: float = param(75.0, "mm", "anterior projection of the mound from the chest wall (ptosis)", gt=10, le=250)
    shape_exponent: float = param(2.0, "-", "profile exponent q of (s^q + (a/P)^q <= 1); 2 = half-ellipsoid", ge=1.2, le=6)
    sag_mm: float = param(8.0, "mm", "caudal shift of the breast tip relative to the base centre", ge=0, le=80)
    skin_thickness_mm: float = param(1.5, "mm", "skin thickness", gt=0.3, le=5)
    muscle_thickness_mm: float = param(12.0, "mm", "pectoral muscle (chest wall) thickness", gt=2, le=40)
    chest_fat_mm: float = param(6.0, "mm", "subcutaneous fat over the chest wall around the breast", ge=0, le=30)
    nipple_radius_mm: float = param(5.0, "mm", "nipple radius", gt=1, le=15)
    nipple_height_mm: float = param(5.0, "mm", "nipple protrusion beyond the mound", gt=1, le=15)
    gland_fraction: float = param(0.3, "-", "fraction of parenchyma labelled fibroglandular (1..3)", ge=0, le=0.9)
    texture_scale_mm: float = param(6.0, "mm", "correlation length of the fat/gland texture", gt=0.5, le=50)
    gland_free_margin_mm: float = param(6.0, "mm", "subcutaneous fat under the skin without gland", ge=0, le=30)
    tumour_size_mm: tuple[float, float, float] = param(
        (25.0, 22.0, 25.0), "mm", "tumour diameters (medio-lateral, antero-posterior, cranio-caudal)")
    tumour_offset_mm: tuple[float, float, float] = param(
        (15.0, 30.0, 10.0), "mm",
        "tumour centre from the base centre: (lateral, anterior from the chest wall, superior)")
    tumour_irregularity: float = param(0.05, "-", "relative amplitude of the tumour surface modulation", ge=0, le=0.3)
    tumour_label: int = param(-3, "-", "tumour label (-3 malignant, -4 benign)", choices=(-3, -4))
    spacing_mm: tuple[float, float, float] = param((0.66, 0.66, 1.4), "mm", "voxel size along L, P, S")
    margin_mm: float = param(12.0, "mm", "air margin around the breast in the field of view", ge=2, le=100)
    base_centre_lps_mm: tuple[float, float, float] | None = param(
        None, "mm", "LPS centre of the breast base on the chest wall (default: x = -95 for R, +95 for L, y = 30, z = 0)")
    noise_sd: float = param(6.0, "-", "MR noise standard deviation (intensity units)", ge=0, le=200)
    bias_amplitude: float = param(0.08, "-", "relative amplitude of the smooth MR bias field", ge=0, le=0.5)

    def problems(self) -> list[str]:
        """Cross-field problems (tumour must fit in the breast, sizes positive)."""
        out = []
        if len(self.tumour_size_mm) != 3 or min(self.tumour_size_mm) <= 0:
            out.append(f"tumour_size_mm = {list(self.tumour_size_mm)}: need three positive diameters")
        if len(self.tumour_offset_mm) != 3:
            out.append(f"tumour_offset_mm = {list(self.tumour_offset_mm)}: need three values")
        if len(self.spacing_mm) != 3 or min(self.spacing_mm) <= 0:
            out.append(f"spacing_mm = {list(self.spacing_mm)}: need three positive voxel sizes")
        elif max(self.spacing_mm) > 4:
            out.append(f"spacing_mm = {list(self.spacing_mm)}: voxels over 4 mm cannot resolve the skin")
        return out

    @property
    def lateral_sign(self) -> float:
        """LPS x sign of the lateral direction: -1 for a right breast, +1 for a left one."""
        return -1.0 if self.side == "R" else 1.0

    @property
    def base_centre(self) -> tuple[float, float, float]:
        """LPS (mm) centre of the breast base on the chest wall (anterior muscle surface)."""
        if self.base_centre_lps_mm is not None:
            return tuple(float(v) for v in self.base_centre_lps_mm)  # type: ignore[return-value]
        return (95.0 * self.lateral_sign, 30.0, 0.0)


def phantom_params(table: dict | None = None, *, where: str = "phantom") -> PhantomParams:
    """Validated :class:`PhantomParams` from a dict (e.g. a TOML table).

    Raises
    ------
    ConfigError
        Naming every bad key, its value and the allowed range.
    """
    obj, problems, warnings = parse_section(PhantomParams, table, where=where)
    problems += warnings  # a misspelt phantom key would silently give another phantom
    if problems:
        raise ConfigError("; ".join(problems))
    return obj
