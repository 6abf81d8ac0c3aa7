"""Tumour contours in the canonical frame: from a polygon, a mask, or a seed point.

Annotations are given in the DICOM's own pixel grid (row, col); they are mapped with
:meth:`MammogramImage.to_canonical_px` before anything else.

Semi-automatic outline from a seed (:func:`tumour_from_seed`)
-------------------------------------------------------------
Masses are denser (brighter) than the tissue around them.  In a square region of
interest around the seed, resampled to ``work_mm``, the image is smoothed and the
candidate regions are the connected components holding the seed of the upper level sets
``{I >= t}``.  The level ``t`` is chosen to maximise the mean gradient magnitude along
the region's boundary (maximum boundary contrast, as in the "optimal iso-contour" mass
segmentation of Kupinski and Giger, IEEE TMI 17(4), 1998, without their constraint
function):

.. math::

    t^* = \\arg\\max_t \\frac{1}{|\\partial R_t|}
          \\sum_{p\\in\\partial R_t} |\\nabla I_\\sigma(p)|

Levels whose region reaches the border of the region of interest (leakage into the
background tissue) are discarded.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage as ndi
from skimage import measure

from regtrack.errors import MammogramError

log = logging.getLogger(__name__)


def polygons_to_canonical(polys, to_canonical) -> list[np.ndarray]:
    """Map polygons (K, 2) of DICOM (row, col) to canonical (row, col); checks shape."""
    if isinstance(polys, np.ndarray) and polys.ndim == 2:
        polys = [polys]
    out = []
    for i, p in enumerate(polys):
        a = np.asarray(p, float)
        if a.ndim != 2 or a.shape[1] != 2 or len(a) < 3 or not np.all(np.isfinite(a)):
            raise MammogramError(f"tumour polygon {i}: needs >= 3 finite [row, col] points, "
                                 f"got shape {a.shape}")
        if len(a) > 3 and np.allclose(a[0], a[-1]):
            a = a[:-1]
        out.append(to_canonical(a))
    return out


def mask_to_contours(mask: np.ndarray, *, min_area_px: float = 4.0) -> list[np.ndarray]:
    """Closed outer contours (row, col; first point not repeated) of each component."""
    lab, n = ndi.label(ndi.binary_fill_holes(mask))
    out = []
    for k in range(1, n + 1):
        comp = lab == k
        if comp.sum() < min_area_px:
            continue
        cs = measure.find_contours(np.pad(comp.astype(np.float32), 1), 0.5)
        c = max(cs, key=len) - 1.0
        out.append(c[:-1] if np.allclose(c[0], c[-1]) else c)
    return out


def tumour_from_seed(image: np.ndarray, spacing, seed_rc, *, roi_mm: float = 60.0,
                     work_mm: float = 0.2, smooth_mm: float = 0.6, n_levels: int = 40,
                     min_radius_mm: float = 1.5) -> tuple[np.ndarray, dict]:
    """Outline a mass around ``seed_rc`` (canonical full-resolution pixels).

    Parameters
    ----------
    image : 2-D float
        Canonical image, values in [0, 1].
    spacing : (2,) float
        (row, col) spacing in mm.
    seed_rc : (2,) float
        A point inside the mass (canonical pixels).
    roi_mm : float
        Side of the square region of interest (mm); the mass must fit inside it.
    work_mm, smooth_mm : float
        Working resolution and Gaussian sigma (mm).
    n_levels : int
        Number of candidate levels between the ROI median and the seed intensity.
    min_radius_mm : float
        Smallest accepted equivalent radius (mm).

    Returns
    -------
    contour : (K, 2) float
        Closed contour, canonical full-resolution (row, col).
    info : dict
        ``level``, ``boundary_gradient``, ``area_mm2``, ``method``.
    """
    from .segment import block_average

    spacing = np.asarray(spacing, float)
    seed = np.asarray(seed_rc, float)
    h, w = image.shape
    if not (0 <= seed[0] <= h - 1 and 0 <= seed[1] <= w - 1):
        raise MammogramError(f"tumour seed {seed.tolist()} lies outside the image ({h}x{w} px)")
    half = np.ceil(0.5 * roi_mm / spacing).astype(int)
    r0, c0 = np.maximum(np.round(seed).astype(int) - half, 0)
    r1, c1 = np.minimum(np.round(seed).astype(int) + half + 1, [h, w])
    small, f = block_average(image[r0:r1, c0:c1], spacing, work_mm)
    wsp = spacing * np.asarray(f, float)
    sm = ndi.gaussian_filter(small.astype(np.float64), smooth_mm / wsp)
    gmag = ndi.gaussian_gradient_magnitude(sm, 0.5)  # small extra smoothing of the gradient
    s = np.clip(np.round(((seed - [r0, c0]) - (np.asarray(f) - 1) / 2) / f).astype(int), 0,
                np.array(sm.shape) - 1)
    rr, cc = np.ogrid[: sm.shape[0], : sm.shape[1]]
    core = ((rr - s[0]) * wsp[0]) ** 2 + ((cc - s[1]) * wsp[1]) ** 2 <= min_radius_mm ** 2
    top, bottom = float(sm[core].mean()), float(np.median(sm))
    if not top > bottom:
        raise MammogramError(f"tumour seed {np.asarray(seed_rc).tolist()}: the seed is not "
                             "brighter than its surroundings; outline the tumour as a polygon "
                             "instead")
    best = (-np.inf, None, None)
    for t in np.linspace(bottom, top, n_levels + 2)[1:-1]:
        lab, _ = ndi.label(sm >= t)
        k = lab[s[0], s[1]]
        if k == 0:
            continue
        reg = ndi.binary_fill_holes(lab == k)
        if reg[0].any() or reg[-1].any() or reg[:, 0].any() or reg[:, -1].any():
            continue  # leaks out of the region of interest
        if reg.sum() * wsp[0] * wsp[1] < np.pi * min_radius_mm ** 2:
            continue
        edge = reg & ~ndi.binary_erosion(reg)
        g = float(gmag[edge].mean())
        if g > best[0]:
            best = (g, t, reg)
    if best[2] is None:
        raise MammogramError(f"tumour seed {np.asarray(seed_rc).tolist()}: no closed outline found "
                             f"within {roi_mm:g} mm; outline the tumour as a polygon or mask")
    g, t, reg = best
    c = mask_to_contours(reg)[0]
    c_full = c * np.asarray(f, float) + (np.asarray(f, float) - 1) / 2 + [r0, c0]
    area = float(reg.sum() * wsp[0] * wsp[1])
    log.info("tumour from seed: level %.3f, boundary gradient %.4f, area %.1f mm^2", t, g, area)
    return c_full, {"level": float(t), "boundary_gradient": g, "area_mm2": area,
                    "method": "seed: maximum boundary-contrast level set"}
