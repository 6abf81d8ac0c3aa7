"""Nipple, anatomical frame and element sizes of the breast model.

Nipple (Lapuebla-Ferri et al.: the most anterior point of the skin in the AP direction),
made robust: the skin vertices of the smoothed outer surface within ``depth`` mm of the
most anterior one form the nipple cap; the nipple is the cap vertex closest (across the AP
axis) to the cap's centroid, weighted by height ``w_i = a_i - (a_max - depth)``.
"""

from __future__ import annotations

import logging

import numpy as np

from regtrack.model.chestwall import SUPERIOR_LPS
from regtrack.model.config import MeshConfig
from regtrack.model.surfaces import Surface
from regtrack.model.types import AnatomicalFrame

log = logging.getLogger(__name__)


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


def target_size(volume_mm3: float, config: MeshConfig, *, c: float = 1.0) -> float:
    """Element size (mm) giving about ``config.target_nodes`` nodes: ``h = (c V / N)^(1/3)``.

    ``c = 1.0`` is measured on remeshed Pelicano breasts (gmsh Delaunay, ``c = 0.92`` without
    tumour refinement; 0.75-1.1 over the eight exams).
    """
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
