"""Settings of the 2-D registration (``[registration]`` in case.toml)."""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param


@dataclass(frozen=True)
class RegistrationConfig:
    """Nipple superposition + golden-section rotation search (Lapuebla-Ferri et al.).

    The nominal angle of both views is 0 deg: the 45 deg pre-rotation of the MLO virtual
    mammogram is built into the MLO plate frame (:mod:`regtrack.virtual.frames`).  Set
    ``nominal_mlo_deg = 45`` only for virtual views made in another frame.
    """

    bracket_deg: float = param(30.0, "deg", "half-width of the rotation search bracket around "
                               "the nominal angle", gt=0.0, le=180.0)
    tol_deg: float = param(1e-3, "deg", "golden-section stops when the bracket is narrower "
                           "than this", gt=0.0, le=5.0)
    resample_mm: float = param(0.5, "mm", "equal arc-length spacing of the resampled "
                               "contours", gt=0.0, le=10.0)
    match: str = param("segment", "-", "closest point on the real contour: 'segment' (on the "
                       "polyline, found from the KD-tree's nearest vertex) or 'point' (nearest "
                       "resampled vertex only)", choices=("segment", "point"))
    coarse_step_deg: float = param(0.0, "deg", "optional coarse scan of the bracket before the "
                                   "golden-section search (0 = pure golden section, as in the "
                                   "paper); guards against a local minimum", ge=0.0, le=30.0)
    nominal_cc_deg: float = param(0.0, "deg", "nominal rotation of the CC virtual view",
                                  ge=-180.0, le=180.0)
    nominal_mlo_deg: float = param(0.0, "deg", "nominal rotation of the MLO virtual view",
                                   ge=-180.0, le=180.0)
    reject_ends_mm: float = param(1.0, "mm", "virtual breast points whose closest real point "
                                  "lies within this distance of an end of the real skin line "
                                  "are left out of F_b (ICP boundary rule: the real line stops "
                                  "at the image edge, the model may reach further); 0 = the "
                                  "paper's plain sum over every point", ge=0.0, le=50.0)
    nipple_search_mm: float = param(50.0, "mm", "a nipple the mammogram reader detected (not "
                                    "one given as nipple_px) is searched along the real skin "
                                    "line, jointly with the rotation, within 3 times the "
                                    "reader's uncertainty along the skin and at most this arc "
                                    "length either side: the point superposed is where the "
                                    "virtual outline fits best (regtrack.registration.align). "
                                    "0 = the detected point, as in the paper", ge=0.0, le=200.0)
    use_tumour: bool = param(True, "-", "search theta_p,t on the tumour contours (required by "
                             "the paper's method; false: theta_p = theta_p,b)")
    min_breast_points: int = param(10, "-", "fewest points accepted in a breast contour", ge=3)
    min_tumour_points: int = param(4, "-", "fewest points accepted in a tumour contour", ge=3)

    def nominal_deg(self, view: str) -> float:
        """Nominal angle (deg) of ``view``."""
        return self.nominal_mlo_deg if view.upper() == "MLO" else self.nominal_cc_deg
