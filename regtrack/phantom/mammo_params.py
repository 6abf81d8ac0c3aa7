"""Settings of the phantom's simulated mammograms (the hidden ground truth).

The truth is simulated with the project's own solver but with settings the pipeline does
*not* assume (its defaults: homogeneous tissue c1 0.54 kPa, nu 0.49, friction 0.1, about
10,000 nodes, no in-plane rotation).  The differences are the model mismatch a correct
pipeline has to live with; they are recorded in the truth file.
"""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param, parse_section
from regtrack.errors import ConfigError


@dataclass(frozen=True)
class MammoTruthParams:
    """Ground-truth simulation, patient positioning and detector of the phantom mammograms.

    Tissue stiffness is heterogeneous: every tetrahedron takes the c1 of the phantom
    label at its centroid (fibroglandular 1-3: ``gland_c1_kpa``; transition 4: the mean
    of fat and gland; fat 5-7 and skin: ``fat_c1_kpa``; tumour: ``tumour_c1_kpa``).
    The image is ``P = ln(I0 / N)`` with ``N ~ Poisson(I0 exp(-A))`` and
    ``A = sum_g mu_g L_g`` the line integral of attenuation (Beer-Lambert).
    """

    seed: int = param(1, "-", "seed of the detector noise", ge=0)
    # --- truth mechanics (differs from the pipeline defaults on purpose)
    element_size_mm: float = param(7.5, "mm", "element size of the truth mesh (1,802 nodes: the bundled "
                                   "case; 4.4 mm, about 11,500 nodes, did not finish its CC compression "
                                   "in 3 min, issue 5)", gt=0.5, le=20)
    surface_step_vox: int = param(4, "voxels", "marching-cubes step of the truth mesh's outer surface", ge=1, le=8)
    fat_c1_kpa: float = param(0.45, "kPa", "neo-Hookean c1 of fat (labels 5-7 and skin)", gt=0, le=100)
    gland_c1_kpa: float = param(1.10, "kPa", "neo-Hookean c1 of fibroglandular tissue (labels 1-3)", gt=0, le=100)
    tumour_c1_kpa: float = param(5.44, "kPa", "neo-Hookean c1 of the tumour", gt=0, le=1000)
    nu: float = param(0.495, "-", "Poisson's ratio of all tissues (pipeline default 0.49)", ge=0.3, lt=0.5)
    force_tol: float = param(1e-4, "-", "Newton relative residual tolerance of the truth run (the stick-slip "
                             "contact stalls near 1e-5 relative, i.e. 0.1 mN on a 6 N breast)", gt=0, lt=0.01)
    initial_increment: float = param(0.1, "-", "first pseudo-time increment of each truth step (the "
                                     "solver default 0.25 stopped the CC compression at t = 0.96 on the "
                                     "bundled label map, 0.1 completes)", gt=0, le=1)
    skin_membrane: bool = param(True, "", "add the skin membrane (as the pipeline does)")
    friction: float = param(0.0, "-", "skin-plate Coulomb friction (pipeline default 0.1; with 0.15 the "
                            "standing-gravity step stalled on the phantom, see the case README)", ge=0, le=1)
    chest_wall_layer_mm: float = param(5.0, "mm", "the breast base lies on the chest wall on a "
                                       "layer of its tissue this thick, whose far side is squeezed "
                                       "with the plates once both hold it "
                                       "(regtrack.mechanics.support; the pipeline's default); 0 "
                                       "clamps it", ge=0, le=100)
    target_D_cc: float = param(0.38, "-", "compression degree of the CC view", gt=0.05, lt=0.8)
    target_D_mlo: float = param(0.28, "-", "compression degree of the MLO view", gt=0.05, lt=0.8)
    # --- patient positioning in the image plane (canonical frame, about the nipple)
    rotation_cc_deg: float = param(5.0, "deg", "in-plane rotation of the CC image about the nipple "
                                   "(sense of regtrack.registration: R = [[c, -s], [s, c]], y down)", ge=-30, le=30)
    rotation_mlo_deg: float = param(-4.0, "deg", "in-plane rotation of the MLO image about the nipple", ge=-30, le=30)
    shift_cc_mm: tuple[float, float] = param((2.0, -3.0), "mm", "in-plane shift (x anterior, y down) of the CC breast")
    shift_mlo_mm: tuple[float, float] = param((-1.5, 4.0), "mm", "in-plane shift (x anterior, y down) of the MLO breast")
    # --- detector and image
    pixel_mm: float = param(0.1, "mm", "pixel size at the detector and at the breast", ge=0.07, le=0.1)
    render_mm: float = param(0.2, "mm", "pixel size of the line-integral rendering (resampled to pixel_mm)", ge=0.05, le=1.0)
    margin_mm: float = param(12.0, "mm", "background around the breast (top, bottom, anterior)", ge=2, le=100)
    chest_cut_mm: float = param(1.0, "mm", "the chest-wall image edge lies this far anterior of the "
                                "most anterior chest-wall point, so the breast leaves the image there", ge=0, le=20)
    quanta_per_pixel: float = param(20000.0, "-", "unattenuated X-ray quanta per pixel (I0)", gt=10)
    mu_fat_per_mm: float = param(0.0456, "1/mm", "attenuation of fat (Johns & Yaffe 1987, 20 keV)", gt=0, le=1)
    mu_gland_per_mm: float = param(0.0802, "1/mm", "attenuation of fibroglandular tissue", gt=0, le=1)
    mu_tumour_per_mm: float = param(0.0844, "1/mm", "attenuation of the tumour (ductal carcinoma)", gt=0, le=1)
    skin_mm: float = param(1.5, "mm", "skin thickness of the skin-line model", ge=0, le=5)
    mu_skin_excess_per_mm: float = param(0.03, "1/mm", "extra attenuation of skin over fat", ge=0, le=1)
    bits_stored: int = param(12, "bits", "detector bit depth", choices=(12, 14))
    compression_ratio: float | None = param(10.0, "-", "JPEG 2000 lossy target ratio (None: lossless)", gt=1, le=100)

    def rotation_deg(self, view: str) -> float:
        return self.rotation_cc_deg if view == "CC" else self.rotation_mlo_deg

    def shift_mm(self, view: str) -> tuple[float, float]:
        return self.shift_cc_mm if view == "CC" else self.shift_mlo_mm

    def target_D(self, view: str) -> float:
        return self.target_D_cc if view == "CC" else self.target_D_mlo

    def problems(self) -> list[str]:
        out = []
        for k in ("shift_cc_mm", "shift_mlo_mm"):
            v = getattr(self, k)
            if len(v) != 2:
                out.append(f"{k} = {list(v)}: need two numbers (x, y) in mm")
        if self.render_mm < self.pixel_mm:
            out.append(f"render_mm = {self.render_mm} is finer than pixel_mm = {self.pixel_mm}; "
                       "render at pixel_mm or coarser")
        return out


def mammo_truth_params(table: dict | None = None, *, where: str = "phantom mammograms") -> MammoTruthParams:
    """Validated :class:`MammoTruthParams` from a dict; unknown keys are errors."""
    obj, problems, warnings = parse_section(MammoTruthParams, table, where=where)
    problems += warnings
    if problems:
        raise ConfigError("; ".join(problems))
    return obj
