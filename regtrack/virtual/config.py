"""Settings of the virtual mammogram (``[virtual]`` overrides in TOML)."""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param


@dataclass(frozen=True)
class VirtualConfig:
    """How a deformed model is turned into a virtual mammogram.

    Linear attenuation defaults are those of Johns & Yaffe (Phys. Med. Biol. 32, 1987)
    at 20 keV: adipose 0.456 /cm, fibroglandular 0.802 /cm, infiltrating ductal carcinoma
    0.844 /cm; the homogenised tissue of the model is taken as a 50/50 mix (0.629 /cm).
    """

    pixel_mm: float = param(0.25, "mm", "pixel size of the projection grid", gt=0.0, le=5.0)
    margin_px: int = param(4, "px", "empty pixels around the projected breast", ge=1, le=100)
    chest_wall_tol_mm: float = param(
        1.0, "mm", "breast-contour points closer than this to the projected chest-wall "
        "faces belong to the chest-wall side and are cut off (open contour)", gt=0.0, le=20.0)
    mu_tissue_per_mm: float = param(0.0629, "1/mm", "linear attenuation of the tissue region",
                                    ge=0.0, le=10.0)
    mu_tumour_per_mm: float = param(0.0844, "1/mm", "linear attenuation of the tumour region",
                                    ge=0.0, le=10.0)
    projection: str = param(
        "auto", "-", "'auto': a cone beam from the mammogram's DICOM source distances "
        "(DistanceSourceToDetector, DistanceSourceToPatient) when present and plausible, else "
        "orthogonal; 'orthogonal': the paper's projection on the lower plate; 'cone': a cone "
        "beam, from source_to_image_mm or the DICOM (regtrack.pipeline.geometry)",
        choices=("auto", "orthogonal", "cone"))
    source_to_image_mm: float = param(
        0.0, "mm", "point-source-to-detector distance for magnified projection; 0 = "
        "orthogonal projection on the lower plate (as in Lapuebla-Ferri et al.)", ge=0.0)
    detector_gap_mm: float = param(
        0.0, "mm", "distance from the lower (receptor) plate down to the detector plane "
        "(only used with a point source)", ge=0.0, le=200.0)
    render: bool = param(True, "-", "also render the X-ray-like image")
