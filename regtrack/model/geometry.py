"""Surfaces of the prepared breast, the nipple and the anatomical frame.

Nipple (Lapuebla-Ferri et al.: the most anterior point of the skin in the AP direction),
made robust: the skin vertices of the smoothed outer surface within ``depth`` mm of the
most anterior one form the nipple cap; the nipple is the cap vertex closest (across the AP
axis) to the cap's centroid, weighted by height ``w_i = a_i - (a_max - depth)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from regtrack.model.chestwall import SUPERIOR_LPS
from regtrack.model.config import MeshConfig
from regtrack.model.prepare import PreparedBreast
from regtrack.model.surfaces import Surface, extract_surface, plane_field, slope_per_mm, smooth_levelset
from regtrack.model.types import AnatomicalFrame

log = logging.getLogger(__name__)


@dataclass
class BreastSurfaces:
    outer: Surface
    tumours: list[Surface]
    tumour_voxel_mm3: list[float]


def surface_step(h_mm: float, spacing: np.ndarray, configured: int) -> int:
    """Marching-cubes step (voxels): the configured one, or ``round(h / (1.3 s))`` when 0."""
    if configured > 0:
        return configured
    return int(max(1, round(h_mm / (1.3 * float(np.mean(spacing))))))


def make_surfaces(prep: PreparedBreast, *, smoothing_mm: float, tumour_smoothing_mm: float,
                  step: int, clearance_mm: float, tumour_steps: list[int] | None = None) -> BreastSurfaces:
    """Outer surface (cut by the planes) and one closed surface per kept tumour (LPS mm)."""
    vol = prep.volume
    sp = vol.spacing
    s = slope_per_mm(smoothing_mm)
    f = smooth_levelset(prep.smooth_mask, smoothing_mm, sp, region=prep.inside,
                        target_count=int(prep.breast.sum()))
    g = f
    for p in prep.planes:
        g = np.minimum(g, plane_field(vol.shape, vol.affine, p, s))
    snap = 0.5 * float(sp.min())
    outer = extract_surface(g, vol.affine, step=step, planes=tuple(prep.planes), snap_mm=0.0)
    # distance (mm) inside the breast voxels to their boundary (cut faces included)
    dist_out = ndimage.distance_transform_edt(np.pad(prep.breast, 1), sampling=sp)[1:-1, 1:-1, 1:-1] - 0.5 * float(np.mean(sp))
    # a coarse marching-cubes step cuts corners by up to half a step: keep tumours clear of it
    base_clearance = clearance_mm
    clearance_mm = clearance_mm + 0.5 * step * float(np.max(sp))
    tumours, tvox = [], []
    st = slope_per_mm(tumour_smoothing_mm)
    pad = np.ceil(3 * tumour_smoothing_mm / sp).astype(int) + 2
    for i, t in enumerate(prep.tumours.kept):
        sl = tuple(slice(max(a.start - p, 0), min(a.stop + p, n)) for a, p, n in zip(t.slices, pad, vol.shape))
        m = prep.tumours.labelled[sl] == t.component
        ft = smooth_levelset(m, tumour_smoothing_mm, sp)
        gt = np.minimum(ft, st * (dist_out[sl] - clearance_mm))
        if gt.max() <= 0:  # the whole tumour lies within the clearance band: keep the base one
            log.warning("tumour %d lies within %.1f mm of the outer surface; clearance reduced to %.1f mm",
                        t.id, clearance_mm, base_clearance)
            gt = np.minimum(ft, st * (dist_out[sl] - base_clearance))
        aff = vol.affine.copy()
        aff[:3, 3] = vol.index_to_world([a.start for a in sl])
        tumours.append(extract_surface(gt, aff, step=tumour_steps[i] if tumour_steps else 1))
        tvox.append(t.volume_mm3)
    return BreastSurfaces(outer, tumours, tvox)


def skin_vertices(surf: Surface, planes, tol_mm: float = 0.05) -> np.ndarray:
    """Boolean mask of the vertices not lying on any cut plane."""
    on = np.zeros(len(surf.verts), bool)
    for p in planes:
        on |= np.abs(p.distance(surf.verts)) < tol_mm
    return ~on


def detect_nipple(points: np.ndarray, anterior: np.ndarray, *, depth_mm: float) -> np.ndarray:
    """Nipple (LPS mm) among skin points: centre of the cap ``depth_mm`` below the apex."""
    a = points @ anterior
    amax = a.max()
    cap = a >= amax - depth_mm
    w = a[cap] - (amax - depth_mm)
    c = (points[cap] * w[:, None]).sum(axis=0) / max(w.sum(), 1e-12)
    rel = points[cap] - c
    across = rel - np.outer(rel @ anterior, anterior)
    best = int(np.argmin(np.linalg.norm(across, axis=1)))
    return points[cap][best]


def make_frame(anterior: np.ndarray, side: str, origin: np.ndarray) -> AnatomicalFrame:
    """Frame with x = ``anterior`` (chest-wall normal), y = patient superior made
    orthogonal to x, z = x * y (patient right)."""
    x = np.asarray(anterior, float) / np.linalg.norm(anterior)
    y = SUPERIOR_LPS - (SUPERIOR_LPS @ x) * x
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return AnatomicalFrame(origin, np.stack([x, y, z]), side)


def target_size(volume_mm3: float, config: MeshConfig, *, c: float = 1.2) -> float:
    """Element size (mm) giving about ``config.target_nodes`` nodes: ``h = (c V / N)^(1/3)``."""
    if config.element_size_mm is not None:
        return float(config.element_size_mm)
    return float((c * volume_mm3 / config.target_nodes) ** (1.0 / 3.0))


def tumour_sizes(volumes_mm3: list[float], h: float, config: MeshConfig) -> list[float]:
    """Element size on each tumour: ``min(h * factor, D / n)`` with ``D`` the equivalent
    diameter ``(6 V / pi)^(1/3)`` and ``n = tumour_min_elements`` (``factor = 1`` when
    ``refine_tumours`` is off)."""
    fac = config.tumour_size_factor if config.refine_tumours else 1.0
    out = []
    for v in volumes_mm3:
        d = (6.0 * v / np.pi) ** (1.0 / 3.0)
        out.append(float(min(h * fac, d / config.tumour_min_elements)))
    return out
