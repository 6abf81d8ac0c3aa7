"""Nipple detection on the open skin contour.

The nipple is taken as the contour point farthest from the chest wall: the image's
chest-wall edge (``x = 0`` in the canonical frame) for CC views, the pectoral line for
MLO views (the posterior nipple line meets the pectoral muscle at a right angle, ACR
BI-RADS positioning criteria).  A flat breast apex makes the farthest point ill-defined
along the contour, so the estimate is refined to the arc-length midpoint of the run of
contour points within ``delta_mm`` of the maximum distance ``d_max``; half of that run's
arc length, ``u``, is reported as the tangential uncertainty (mm), and

.. math::  \\text{confidence} = \\frac{1}{1 + (u / u_0)^2}, \\qquad u_0 = 10\\ \\text{mm}.
"""

from __future__ import annotations

import numpy as np


ChestWall = tuple[np.ndarray, np.ndarray]


def chest_wall_distance(xy: np.ndarray, *, chest_wall: ChestWall | None) -> np.ndarray:
    """Distance (mm) of points ``xy`` (N, 2) from the chest wall.

    ``chest_wall`` is a line given by a point and a unit normal pointing anteriorly (mm);
    None means the canonical chest-wall edge ``x = 0``.
    """
    if chest_wall is None:
        return xy[:, 0].copy()
    p, n = chest_wall
    return (xy - p) @ n


def detect_nipple(contour_xy: np.ndarray, *, chest_wall: ChestWall | None = None,
                  delta_mm: float = 1.0, u0_mm: float = 10.0) -> tuple[np.ndarray, dict]:
    """Detect the nipple on an open contour.

    Parameters
    ----------
    contour_xy : (M, 2) float
        Open skin contour (mm, canonical frame).
    chest_wall : (point, unit normal) in mm, optional
        Chest-wall line (see :func:`chest_wall_distance`).
    delta_mm : float
        Distance band below the maximum that counts as "farthest" (mm).
    u0_mm : float
        Uncertainty scale of the confidence (mm).

    Returns
    -------
    nipple : (2,) float
        A point of ``contour_xy`` (mm).
    info : dict
        ``index``, ``distance_to_chest_wall_mm``, ``tangential_uncertainty_mm``,
        ``confidence`` in (0, 1], ``method``.
    """
    d = chest_wall_distance(contour_xy, chest_wall=chest_wall)
    imax = int(np.argmax(d))
    near = d >= d[imax] - delta_mm
    # contiguous run around imax
    lo = imax
    while lo > 0 and near[lo - 1]:
        lo -= 1
    hi = imax
    while hi < len(d) - 1 and near[hi + 1]:
        hi += 1
    seg = contour_xy[lo:hi + 1]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(seg, axis=0), axis=1))])
    k = lo + int(np.argmin(np.abs(s - 0.5 * s[-1])))
    u = 0.5 * float(s[-1])
    conf = 1.0 / (1.0 + (u / u0_mm) ** 2)
    return contour_xy[k].copy(), {
        "index": k,
        "distance_to_chest_wall_mm": float(d[k]),
        "tangential_uncertainty_mm": u,
        "confidence": float(conf),
        "method": "detected: farthest contour point from the "
                  + ("chest-wall edge" if chest_wall is None else "pectoral line"),
    }
