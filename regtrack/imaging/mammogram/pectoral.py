"""Pectoral muscle of an MLO view (canonical orientation: muscle in the top-left corner).

The muscle edge is modelled as the straight line through ``(x0, 0)`` on the top edge
and ``(0, y0)`` on the chest-wall edge (working-grid pixels),

.. math::  \\frac{x}{x_0} + \\frac{y}{y_0} = 1,

the usual approximation of the pectoral boundary on MLO views (e.g. Kwok et al., IEEE
TMI 23(9), 2004, start from such a line).  The muscle is brighter than the breast tissue
in front of it, so the line is chosen by exhaustive search over ``(x0, y0)`` maximising
the mean intensity drop across it,

.. math::  S(x_0, y_0) = \\frac{1}{N}\\sum_k -\\nabla I_\\sigma(p_k)\\cdot n ,

with ``p_k`` points of the segment inside the tissue and ``n`` its unit normal pointing
away from the corner.  The search covers ``x0`` in [5 %, 100 %] of the tissue's extent
along the top edge and ``y0`` in [25 %, 100 %] of its height (the muscle edge of an
adequately positioned MLO reaches at least the upper quarter of the breast).  The line
is accepted when the muscle triangle is brighter than a band in front of it by at least
``min_contrast`` (image units).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage as ndi

log = logging.getLogger(__name__)


def _tissue_extent(tissue: np.ndarray) -> tuple[int, int]:
    """(rightmost tissue column in the top rows, lowest tissue row)."""
    top_rows = tissue[: max(1, tissue.shape[0] // 50)]
    cols = np.nonzero(top_rows.any(axis=0))[0]
    rows = np.nonzero(tissue.any(axis=1))[0]
    return (int(cols.max()) if cols.size else 0), (int(rows.max()) if rows.size else 0)


def find_pectoral(smooth: np.ndarray, tissue: np.ndarray, spacing, *, grad_sigma_mm: float = 1.5,
                  n_candidates: int = 48, band_mm: float = 8.0,
                  min_contrast: float = 0.03) -> dict | None:
    """Find the pectoral line of a canonical MLO view.

    Parameters
    ----------
    smooth : 2-D float
        Smoothed working-grid image, values in [0, 1].
    tissue : 2-D bool
        Breast + muscle mask on the same grid.
    spacing : (2,) float
        Working-grid spacing (row, col), mm.

    Returns
    -------
    dict or None
        ``{"x0_px", "y0_px"`` (working grid), ``"score"``, ``"contrast"`` (muscle minus
        band mean intensity), ``"mask"`` (bool, the muscle triangle within the tissue)}``;
        None when no line reaches ``min_contrast``.
    """
    h, w = tissue.shape
    xmax, ymax = _tissue_extent(tissue)
    if xmax < 4 or ymax < 4:
        log.info("pectoral: tissue does not reach the top-left corner; none removed")
        return None
    sig = grad_sigma_mm / np.asarray(spacing, float)
    gy = ndi.gaussian_filter(smooth, sig, order=(1, 0)) / spacing[0]
    gx = ndi.gaussian_filter(smooth, sig, order=(0, 1)) / spacing[1]
    x0s = np.linspace(0.05 * xmax, 1.0 * xmax, n_candidates)
    y0s = np.linspace(0.25 * ymax, 1.0 * ymax, n_candidates)
    X0, Y0 = np.meshgrid(x0s, y0s, indexing="ij")
    t = np.linspace(0.1, 0.9, 64)
    # sample points p = (1-t)(x0, 0) + t (0, y0)
    px = (1 - t)[None, None, :] * X0[..., None]
    py = t[None, None, :] * Y0[..., None]
    nx, ny = 1.0 / X0, 1.0 / Y0
    nn = np.hypot(nx * spacing[1], ny * spacing[0])
    nx, ny = nx / nn, ny / nn  # unit normal in mm-scaled coordinates
    coords = np.stack([py.ravel(), px.ravel()])
    g = -(ndi.map_coordinates(gx, coords, order=1) * np.repeat(nx.ravel(), t.size)
          + ndi.map_coordinates(gy, coords, order=1) * np.repeat(ny.ravel(), t.size))
    inside = ndi.map_coordinates(tissue.astype(np.float32), coords, order=0) > 0.5
    g = np.where(inside, g, 0.0).reshape(X0.shape + t.shape)
    frac = inside.reshape(g.shape).mean(-1)
    score = g.sum(-1) / t.size * np.where(frac > 0.5, 1.0, 0.0)
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    x0, y0 = float(X0[i, j]), float(Y0[i, j])
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    lhs = xx / x0 + yy / y0
    muscle = (lhs <= 1.0) & tissue
    # band in front of the line, band_mm wide (distance to the line in mm)
    dist_mm = (lhs - 1.0) / np.hypot(1.0 / (x0 * spacing[1]), 1.0 / (y0 * spacing[0]))
    band = (dist_mm > 0) & (dist_mm <= band_mm) & tissue
    if not muscle.any() or not band.any():
        return None
    contrast = float(smooth[muscle].mean() - smooth[band].mean())
    if contrast < min_contrast:
        log.info("pectoral: best line contrast %.3f < %.3f; no muscle removed", contrast,
                 min_contrast)
        return None
    log.debug("pectoral: x0 %.1f px, y0 %.1f px, contrast %.3f", x0, y0, contrast)
    return {"x0_px": x0, "y0_px": y0, "score": float(score[i, j]), "contrast": contrast,
            "mask": muscle}
