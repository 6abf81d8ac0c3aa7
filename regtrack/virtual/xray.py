"""X-ray-like rendering of a deformed tetrahedral mesh: line integrals of attenuation.

For a ray along the plate normal ``n`` through pixel ``q`` the path length through a
closed region ``Omega_g`` (all tets of attenuation group ``g``) is obtained from its
boundary alone (divergence theorem along the ray):

.. math::

    L_g(q) = \\sum_{f \\in \\partial\\Omega_g,\\, q \\in \\pi(f)} s_f\\, h_f(q),
    \\qquad s_f = \\operatorname{sign}(\\nu_f \\cdot n)

where ``h_f(q)`` is the height of face ``f`` above the plate at ``q`` (linear over the
projected triangle ``pi(f)``) and ``nu_f`` its outward normal: exit faces add their
height, entry faces subtract it.  The image is the line integral

.. math:: A(q) = \\sum_g \\mu_g L_g(q)

(Beer-Lambert: the detected intensity is ``I0 exp(-A)``); the displayed image is the
log-transformed intensity ``ln(I0 / I) / max = A / max A``, as on a processed ("for
presentation") mammogram: dense is bright, and contrast does not saturate in thick breasts.

Point source (optional).  With a source at distance ``SID`` above the detector plane
(foot ``(X0, Y0)``), the projective map

.. math::

    X' = X_0 + (X - X_0) \\frac{SID}{h_s - h}, \\quad
    Y' = Y_0 + (Y - Y_0) \\frac{SID}{h_s - h}, \\quad
    w = \\frac{1}{h_s - h}

(``h_s`` the source height) sends the diverging rays to parallel lines and planes to
planes, so tets stay tets and ``w`` is linear over every mapped face; the height is
recovered per pixel as ``h = h_s - 1/w`` and the oblique path is longer by
``sqrt(1 + r^2 / SID^2)`` (``r`` the distance from the pixel to the foot).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regtrack.virtual.raster import Grid, rasterise
from regtrack.virtual.surface import boundary_faces


@dataclass(frozen=True)
class PointSource:
    """X-ray focal spot above the detector, in plate coordinates (mm).

    ``foot`` is the (X, Y) foot of the perpendicular from the source to the detector,
    ``sid`` the source-to-image distance and ``detector_h`` the height of the detector
    plane in the plate frame (``-gap``: below the lower plate).
    """

    foot: tuple[float, float]
    sid: float
    detector_h: float = 0.0

    @property
    def height(self) -> float:
        """Source height h_s above the lower plate (mm)."""
        return self.detector_h + self.sid

    def magnification(self, h) -> np.ndarray:
        """Magnification ``SID / (h_s - h)`` of a point at height ``h`` (mm)."""
        return self.sid / (self.height - np.asarray(h, float))


def perspective(local: np.ndarray, source: PointSource) -> np.ndarray:
    """Map (N, 3) plate coordinates (X, Y, h) to (X', Y', w) (see module docstring)."""
    local = np.asarray(local, float)
    gap = source.height - local[:, 2]
    if np.any(gap <= 0):
        raise ValueError("points at or above the X-ray source: increase source_to_image_mm")
    m = source.sid / gap
    fx, fy = source.foot
    return np.stack([fx + (local[:, 0] - fx) * m, fy + (local[:, 1] - fy) * m, 1.0 / gap], 1)


def projected_xy(local: np.ndarray, source: PointSource | None) -> np.ndarray:
    """(N, 2) image-plane coordinates (mm) of plate coordinates, orthogonal or magnified."""
    local = np.asarray(local, float)
    return local[:, :2].copy() if source is None else perspective(local, source)[:, :2]


def path_lengths(local: np.ndarray, tets: np.ndarray, groups: np.ndarray, grid: Grid, *,
                 source: PointSource | None = None) -> dict[int, np.ndarray]:
    """Path length (mm) through each group of tets, per pixel of ``grid``.

    Parameters
    ----------
    local : (N, 3) float
        Deformed node coordinates in the plate frame (X, Y, h), mm.
    tets : (E, 4) int
    groups : (E,) int
        Group of each tet (e.g. 1 tissue, 2 tumour, or an attenuation class).
    grid : Grid
        Image grid in the detector plane (mm).
    source : PointSource, optional
        Point source; None for parallel rays along the plate normal.

    Returns
    -------
    dict
        ``{group: (H, W) path length in mm}``.
    """
    local = np.asarray(local, float)
    tets = np.asarray(tets, np.int64)
    groups = np.asarray(groups)
    if source is None:
        q, post = local, None
        sec = 1.0
    else:
        q = perspective(local, source)
        hs = source.height

        def post(w: np.ndarray) -> np.ndarray:
            return hs - 1.0 / w  # height (mm) back from w = 1 / (h_s - h)

        xc, yc = grid.centres()
        r2 = (xc[None, :] - source.foot[0]) ** 2 + (yc[:, None] - source.foot[1]) ** 2
        sec = np.sqrt(1.0 + r2 / source.sid**2)
    out: dict[int, np.ndarray] = {}
    for g in np.unique(groups):
        faces = boundary_faces(tets[groups == g], q)
        p = q[faces]
        area2 = ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                 - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
        _, acc = rasterise(q[:, :2], faces, grid, values=q[:, 2], weights=np.sign(area2),
                           post=post)
        out[int(g)] = np.maximum(acc, 0.0) * sec
    return out


def render(lengths: dict[int, np.ndarray], mu_per_mm: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
    """Line integral ``A = sum_g mu_g L_g`` (dimensionless) and the display image in [0, 1]."""
    shape = next(iter(lengths.values())).shape if lengths else (0, 0)
    a = np.zeros(shape)
    for g, length in lengths.items():
        a += mu_per_mm.get(g, 0.0) * length
    top = float(a.max()) if a.size else 0.0
    img = a / top if top > 0 else np.zeros_like(a)
    return a, np.clip(img, 0.0, 1.0)
