"""Open breast contour (the skin line) from a breast mask.

The boundary of the mask is traced with marching squares at level 0.5 (sub-pixel, so the
enclosed area equals the pixel count up to the corner cut-offs).  Boundary points that
lie on the image border (where the breast leaves the film: chest-wall edge, or cut by
the top/bottom edge) or on the pectoral line are not skin; the skin line is the longest
run of the remaining points, ordered from its top end to its bottom end.
"""

from __future__ import annotations

import numpy as np
from skimage import measure

from regtrack.errors import MammogramError


def _outer_boundary(mask: np.ndarray) -> np.ndarray:
    """Closed outer boundary (N, 2) (row, col) of the largest component, no repeat."""
    padded = np.pad(mask.astype(np.float32), 1)
    cs = measure.find_contours(padded, 0.5)
    if not cs:
        raise MammogramError("mammogram: empty breast mask; no contour")
    c = max(cs, key=lambda a: abs(polygon_area(a)))
    c = c - 1.0
    if np.allclose(c[0], c[-1]):
        c = c[:-1]
    return c


def polygon_area(rc: np.ndarray) -> float:
    """Signed shoelace area of a closed polygon given as (N, 2) points (units^2)."""
    y, x = rc[:, 0], rc[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _longest_true_run(flags: np.ndarray) -> np.ndarray:
    """Indices of the longest cyclic run of True in ``flags`` (in order)."""
    n = flags.size
    if flags.all():
        return np.arange(n)
    start = int(np.argmin(flags))  # a False entry: unroll the cycle there
    rolled = np.roll(flags, -start)
    best, best_len, i = (0, 0), 0, 0
    while i < n:
        if rolled[i]:
            j = i
            while j < n and rolled[j]:
                j += 1
            if j - i > best_len:
                best, best_len = (i, j), j - i
            i = j
        else:
            i += 1
    return (np.arange(best[0], best[1]) + start) % n


def open_contour(mask: np.ndarray, *, pectoral: dict | None = None,
                 border_tol_px: float = 0.25, pectoral_tol_px: float = 1.5,
                 chest_band_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Skin line of ``mask`` as an open polyline, and the closed boundary.

    Parameters
    ----------
    mask : 2-D bool
        Breast mask (canonical orientation, chest wall on the left).
    pectoral : dict, optional
        Pectoral line ``{"x0_px", "y0_px"}`` on the same grid (MLO).
    border_tol_px, pectoral_tol_px : float
        Points closer than this to the image border / pectoral line are not skin.
    chest_band_px : float
        Width of a film-edge band cut off along the chest-wall edge
        (:func:`~regtrack.imaging.mammogram.segment.remove_border_strips`): contour points
        at either end that lie within it are the cut, not skin, and are trimmed.

    Returns
    -------
    skin : (M, 2) float
        (row, col) points from the top end to the bottom end.
    closed : (N, 2) float
        The full closed boundary (row, col).
    """
    closed = _outer_boundary(mask)
    h, w = mask.shape
    r, c = closed[:, 0], closed[:, 1]
    # the padded trace puts border points exactly half a pixel outside the grid
    lim = 0.5 - border_tol_px
    on_border = (r < -lim) | (c < -lim) | (r > h - 1 + lim) | (c > w - 1 + lim)
    keep = ~on_border
    if pectoral is not None:
        x0, y0 = pectoral["x0_px"], pectoral["y0_px"]
        d = (c / x0 + r / y0 - 1.0) / np.hypot(1.0 / x0, 1.0 / y0)
        keep &= d > pectoral_tol_px
    if keep.sum() < 5:
        raise MammogramError("mammogram: the breast mask has no skin boundary (it fills the image "
                             "or touches the borders everywhere)")
    idx = _longest_true_run(keep)
    skin = closed[idx]
    if chest_band_px > 0:
        inside = skin[:, 1] < chest_band_px + 0.5
        lo, hi = 0, len(skin)
        while lo < hi - 5 and inside[lo]:
            lo += 1
        while hi - 1 > lo + 5 and inside[hi - 1]:
            hi -= 1
        skin = skin[lo:hi]
    if skin[0, 0] > skin[-1, 0]:
        skin = skin[::-1]
    return skin, closed


def smooth_polyline(xy: np.ndarray, *, sigma_mm: float) -> np.ndarray:
    """Gaussian smoothing of an open polyline along its arc length (ends kept in place).

    The traced skin line has the staircase and the noise of the pixel grid; smoothing
    with ``sigma_mm`` moves a curve of radius ``R`` inwards by about
    ``sigma^2 / (2 R)`` (0.01 mm for sigma = 1 mm and R = 50 mm), far below a pixel.
    """
    from scipy.ndimage import gaussian_filter1d

    if sigma_mm <= 0 or len(xy) < 5:
        return xy.copy()
    step = float(np.mean(np.linalg.norm(np.diff(xy, axis=0), axis=1)))
    s = sigma_mm / max(step, 1e-9)
    out = np.column_stack([gaussian_filter1d(xy[:, k], s, mode="nearest") for k in range(2)])
    out[0], out[-1] = xy[0], xy[-1]
    return out
