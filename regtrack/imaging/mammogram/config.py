"""Parameters of the real-mammogram extraction (one typed, validated section).

Parse a TOML table with :func:`regtrack.config.parse_section`::

    cfg, problems, warnings = parse_section(MammogramConfig, {"open_mm": 3.0},
                                            where="case.toml [mammogram]")
"""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.config import param


@dataclass(frozen=True)
class MammogramConfig:
    """Segmentation, contour and nipple parameters (lengths in mm of the breast plane)."""

    working_spacing_mm: float = param(0.5, "mm", "pixel size of the segmentation grid "
                                      "(block averaging; never upsampled)", gt=0.0, le=5.0)
    smooth_mm: float = param(0.5, "mm", "Gaussian sigma before thresholding", ge=0.0, le=10.0)
    threshold_rel: float = param(0.05, "-", "breast threshold above the background, as a "
                                 "fraction of the foreground-background contrast", gt=0.0, lt=1.0)
    threshold_noise: float = param(6.0, "-", "minimum threshold above the background in units "
                                   "of the background's robust standard deviation", ge=0.0)
    open_mm: float = param(2.0, "mm", "radius of the opening that detaches burned-in labels "
                           "and thin film edges", gt=0.0, le=20.0)
    strip_max_mm: float = param(15.0, "mm", "film-edge bands narrower than this along a border "
                                "are cut off", ge=0.0, le=100.0)
    strip_min_run_mm: float = param(15.0, "mm", "minimum length of such a band along the border",
                                    gt=0.0)
    remove_pectoral: bool = param(True, "", "remove the pectoral muscle on MLO views")
    pectoral_min_contrast: float = param(0.03, "-", "minimum muscle-minus-breast mean intensity "
                                         "(image in [0, 1]) to accept a pectoral line", ge=0.0)
    contour_sigma_mm: float = param(1.0, "mm", "smoothing of the skin line along its arc length",
                                    ge=0.0, le=10.0)
    nipple_delta_mm: float = param(1.0, "mm", "band below the farthest contour point whose "
                                   "midpoint is the nipple", gt=0.0, le=20.0)
    seed_roi_mm: float = param(60.0, "mm", "side of the region searched around a tumour seed",
                               gt=2.0, le=300.0)
