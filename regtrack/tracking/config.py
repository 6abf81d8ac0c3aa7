"""Settings of lesion tracking (``regtrack track``)."""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param


@dataclass(frozen=True)
class TrackingConfig:
    """Sampling of the projection ray and the uncertainty models (:mod:`.uncertainty`,
    :mod:`.lesions`); ``[tracking]`` in case.toml."""

    ray_step_mm: float = param(0.25, "mm", "spacing of the samples along the projection ray "
                               "through the compressed source view (CC -> MLO)", gt=0.0, le=5.0)
    residual_scale_mm: float = param(25.0, "mm", "length scale L of the Gaussian weights "
                                     "exp(-r^2 / 2 L^2) that localise the registration residual "
                                     "around a predicted point", gt=0.0, le=500.0)
    min_residual_mm: float = param(0.5, "mm", "floor of the registration-residual term (about "
                                   "one contour resampling step: the residual is not resolved "
                                   "below it)", ge=0.0, le=20.0)
    max_outside_mm: float = param(2.0, "mm", "an MRI point up to this far outside the meshed "
                                  "breast is snapped onto the mesh (recorded); farther is an "
                                  "error", ge=0.0, le=50.0)
    correlation_mm: float = param(10.0, "mm", "correlation length L_c of the contour residuals: "
                                  "the angular uncertainty of the breast registration counts one "
                                  "independent residual per L_c of contour "
                                  "(regtrack.tracking.uncertainty.angular_sigma)", gt=0.0, le=500.0)
    material_rel: float = param(0.16, "-", "relative sensitivity alpha of the lesion's in-plane "
                                "shift to the tissue's c1 and nu (the median measured by "
                                "re-simulation; regtrack.tracking.uncertainty)", ge=0.0, le=2.0)
    degree_sigma: float = param(0.05, "-", "1-sigma uncertainty of the compression degree D "
                                "when it is the protocol's nominal value (no DICOM thickness)",
                                ge=0.0, le=0.5)
    thickness_sigma_mm: float = param(3.0, "mm", "1-sigma uncertainty of the DICOM's "
                                      "BodyPartThickness (the displayed paddle height)", ge=0.0,
                                      le=50.0)
    c1_rel_sigma: float = param(0.3, "-", "3-D tracking (track --view --uncertainty): 1-sigma "
                                "relative uncertainty of the tissue c1 (a stated estimate)",
                                ge=0.0, le=2.0)
    nu_sigma: float = param(0.02, "-", "3-D tracking (track --view --uncertainty): 1-sigma "
                            "uncertainty of Poisson's ratio nu (a stated estimate)", ge=0.0,
                            le=0.2)
