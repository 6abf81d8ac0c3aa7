"""Geometry of the prone breast phantom: grid, breast mound, nipple, skin, muscle, tumour.

Local breast coordinates (mm) of an LPS point ``x``, relative to the base centre ``c``:

* ``u = s_lat * (x_L - c_L)``: lateral offset (``s_lat = -1`` for a right breast);
* ``a = c_P - x_P``: anterior distance from the chest wall (the prone breast hangs toward
  -P);
* ``v = x_S - c_S``: superior offset.

Breast mound (sheared half super-ellipsoid with base semi-axes ``R_u``, ``R_v``,
projection ``P``, exponent ``q`` and tip sag ``σ``)::

    v_c(a) = -σ (a / P)^2
    s(u, v, a) = sqrt((u / R_u)^2 + ((v - v_c(a)) / R_v)^2)
    inside  <=>  0 <= a  and  s^q + (a / P)^q <= 1

The shear ``v -> v - v_c(a)`` preserves volume, so for ``q = 2`` the mound volume is
``V = (2/3) π R_u R_v P``; in general ``V = π R_u R_v P Γ(1+1/q) Γ(1+2/q) / Γ(1+3/q)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import gamma, pi

import numpy as np
from scipy import ndimage

from regtrack.errors import ConfigError
from regtrack.imaging.volume import make_affine
from regtrack.phantom.params import PhantomParams


@dataclass(frozen=True)
class Grid:
    """Axis-aligned LPS voxel grid (axis 0 = L, 1 = P, 2 = S)."""

    shape: tuple[int, int, int]
    origin: np.ndarray  # LPS of voxel (0, 0, 0), mm
    spacing: np.ndarray  # mm

    @property
    def affine(self) -> np.ndarray:
        return make_affine(self.origin, self.spacing)

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LPS coordinate (mm) of the voxel centres along each axis."""
        return tuple(self.origin[d] + self.spacing[d] * np.arange(self.shape[d]) for d in range(3))  # type: ignore[return-value]


def make_grid(p: PhantomParams) -> Grid:
    """Smallest grid holding the muscle, the breast, the nipple and ``margin_mm`` of air."""
    c = np.asarray(p.base_centre)
    sp = np.asarray(p.spacing_mm, float)
    ru, rv = p.base_width_mm / 2, p.base_height_mm / 2
    half_l = ru + p.margin_mm
    lo = np.array([c[0] - half_l,
                   c[1] - p.projection_mm - p.nipple_height_mm - p.margin_mm,
                   c[2] - rv - p.sag_mm - p.margin_mm])
    hi = np.array([c[0] + half_l, c[1] + p.muscle_thickness_mm + 4.0, c[2] + rv + p.margin_mm])
    shape = tuple(int(v) for v in np.ceil((hi - lo) / sp).astype(int) + 1)
    return Grid(shape=shape, origin=lo, spacing=sp)  # type: ignore[arg-type]


def local_coords(grid: Grid, p: PhantomParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Broadcastable local coordinates ``(u, a, v)`` (mm) of the voxel centres."""
    x, y, z = grid.axes()
    c = p.base_centre
    u = (p.lateral_sign * (x - c[0]))[:, None, None]
    a = (c[1] - y)[None, :, None]
    v = (z - c[2])[None, None, :]
    return u, a, v


def centreline_v(a, p: PhantomParams):
    """Superior offset (mm) of the mound's axis at depth ``a``: ``-σ (a/P)^2``."""
    return -p.sag_mm * (np.clip(a, 0, None) / p.projection_mm) ** 2


def breast_mound(u, a, v, p: PhantomParams) -> np.ndarray:
    """Boolean mask of the breast mound (see the module docstring)."""
    ru, rv, q = p.base_width_mm / 2, p.base_height_mm / 2, p.shape_exponent
    s = np.sqrt((u / ru) ** 2 + ((v - centreline_v(a, p)) / rv) ** 2)
    return (a >= 0) & (s**q + (np.clip(a, 0, None) / p.projection_mm) ** q <= 1.0)


def mound_volume_mm3(p: PhantomParams) -> float:
    """Analytic mound volume ``π R_u R_v P Γ(1+1/q) Γ(1+2/q) / Γ(1+3/q)`` (mm^3)."""
    q = p.shape_exponent
    return (pi * p.base_width_mm / 2 * p.base_height_mm / 2 * p.projection_mm
            * gamma(1 + 1 / q) * gamma(1 + 2 / q) / gamma(1 + 3 / q))


def nipple_tip_local(p: PhantomParams) -> np.ndarray:
    """Local ``(u, a, v)`` (mm) of the nipple tip."""
    return np.array([0.0, p.projection_mm + p.nipple_height_mm, centreline_v(p.projection_mm, p)])


def nipple(u, a, v, p: PhantomParams) -> np.ndarray:
    """Nipple: half-ellipsoid of radius ``r_n`` and height ``h_n`` on the mound's tip."""
    tip_v = centreline_v(p.projection_mm, p)
    r, h = p.nipple_radius_mm, p.nipple_height_mm
    da = a - p.projection_mm
    return (da >= -r) & ((u / r) ** 2 + ((v - tip_v) / r) ** 2 + (np.clip(da, 0, None) / h) ** 2 <= 1.0)


def local_to_lps(local, p: PhantomParams) -> np.ndarray:
    """LPS (mm) of local ``(u, a, v)`` points (..., 3)."""
    local = np.asarray(local, float)
    c = np.asarray(p.base_centre)
    return np.stack([c[0] + p.lateral_sign * local[..., 0], c[1] - local[..., 1], c[2] + local[..., 2]], axis=-1)


def tumour_mask(grid: Grid, p: PhantomParams, rng: np.random.Generator) -> np.ndarray:
    """Tumour: ellipsoid of diameters ``tumour_size_mm`` (LR, AP, SI) with a smooth modulation.

    A point at normalised radius ``r = |((x - t) / s_half)|`` and unit direction ``n`` is
    inside when ``r <= 1 + ε h(n)``, with ``h(n) = tanh(n·M n + b·n)`` (``M``, ``b`` random,
    seeded), ``|h| < 1``, so each extent stays within ``±ε`` of the requested diameter.
    """
    centre = local_to_lps(np.array([p.tumour_offset_mm[0], p.tumour_offset_mm[1], p.tumour_offset_mm[2]]), p)
    half = np.asarray(p.tumour_size_mm, float) / 2
    x, y, z = grid.axes()
    dx = ((x - centre[0]) / half[0])[:, None, None]
    dy = ((y - centre[1]) / half[1])[None, :, None]
    dz = ((z - centre[2]) / half[2])[None, None, :]
    r = np.sqrt(dx**2 + dy**2 + dz**2)
    m = rng.normal(size=(3, 3))
    m = (m + m.T) / 2
    b = rng.normal(size=3)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = [d / np.where(r > 0, r, 1.0) for d in (dx, dy, dz)]
    quad = sum(m[i, j] * n[i] * n[j] for i in range(3) for j in range(3)) + sum(b[i] * n[i] for i in range(3))
    return r <= 1.0 + p.tumour_irregularity * np.tanh(quad)


def skin_depth(body: np.ndarray, air: np.ndarray, grid: Grid) -> np.ndarray:
    """Distance (mm) from each voxel centre to the nearest air voxel centre."""
    return ndimage.distance_transform_edt(~air, sampling=grid.spacing)


def check_tumour_inside(tumour: np.ndarray, inner: np.ndarray, p: PhantomParams) -> None:
    """Raise ConfigError if the tumour leaves the breast interior (skin and chest wall excluded)."""
    if not tumour.any():
        raise ConfigError(f"phantom tumour_size_mm = {list(p.tumour_size_mm)}: tumour smaller than one voxel")
    outside = int((tumour & ~inner).sum())
    if outside:
        raise ConfigError(
            f"phantom tumour_offset_mm = {list(p.tumour_offset_mm)} with tumour_size_mm = "
            f"{list(p.tumour_size_mm)}: {outside} tumour voxels fall outside the breast parenchyma "
            "(skin, chest wall or air); move the tumour inward or make it smaller"
        )
