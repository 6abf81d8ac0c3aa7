"""Breast thickness between the plates and the compression degree D.

Compression degree (Lapuebla-Ferri et al.: the relative reduction of the breast
thickness between the undeformed and the deformed configuration)

.. math::

    D = \\frac{T_0 - T}{T_0}

* ``T_0`` (mm): thickness of the *uncompressed* breast between the plates: the extent,
  along the plate normal ``n``, of the surface nodes lying over the plate (anterior to its
  chest-wall edge) above the lower plate face, taken when the compression plate first
  touches the breast (standing, on the lower plate and hanging on its chest-wall base:
  :mod:`regtrack.mechanics.protocol_run`);
* ``T`` (mm): the compressed thickness = the gap between the two plate faces.

This is the clinical definition (the compressed breast thickness read on the unit) and
it counts only the compressed part of the breast, never the chest-wall base (docs/design.md,
"Thickness means the compressed part").  A second, volumetric measure is reported
beside it: the *mean* thickness ``T_mean = V / A_n`` of the breast over the plate, with
``V`` its volume and ``A_n`` its area projected along ``n``
(``A_n = 1/2 sum_f |a_f . n|`` for the outer triangle area vectors ``a_f``: each line
along ``n`` crosses the surface twice), giving ``D_mean = 1 - T_mean / T_mean,0``.
"""

from __future__ import annotations

import numpy as np

from regtrack.errors import ResultCheckError


def heights(points: np.ndarray, origin, normal) -> np.ndarray:
    """Signed height (mm) of (N, 3) points above the plane through ``origin`` along ``normal``."""
    n = np.asarray(normal, float)
    return (np.asarray(points, float) - np.asarray(origin, float)) @ (n / np.linalg.norm(n))


def thickness_between_plates(points: np.ndarray, nodes: np.ndarray, *, lower_origin, normal,
                             over_plate: np.ndarray | None = None) -> float:
    """Uncompressed thickness ``T_0`` (mm): max height of ``nodes`` above the lower plate.

    Parameters
    ----------
    points : (N, 3) float
        Current node positions (mm).
    nodes : (M,) int
        Skin nodes.
    lower_origin : (3,) float
        A point of the lower plate face (mm).
    normal : (3,) float
        Plate normal ``n`` (lower -> upper plate).
    over_plate : (M,) bool, optional
        Which of ``nodes`` lie over the plate (anterior to its chest-wall edge).
    """
    nodes = np.asarray(nodes)
    sel = nodes if over_plate is None else nodes[np.asarray(over_plate, bool)]
    if len(sel) == 0:
        raise ResultCheckError("compression: no surface node lies over the plates; move the "
                               "plates' chest-wall edge ([protocol] posterior_edge_mm)")
    return float(heights(points[sel], lower_origin, normal).max())


def compression_degree(t0_mm: float, t_mm: float) -> float:
    """``D = (T_0 - T) / T_0`` (fraction, 0..1) from the thicknesses in mm."""
    if not t0_mm > 0:
        raise ResultCheckError(f"compression: uncompressed thickness T0 = {t0_mm} mm must be > 0")
    return float((t0_mm - t_mm) / t0_mm)


def gap_for_degree(t0_mm: float, degree: float) -> float:
    """Plate gap ``T = (1 - D) T_0`` (mm) that gives the compression degree ``D``."""
    return float((1.0 - degree) * t0_mm)


def mean_thickness(points: np.ndarray, tets: np.ndarray, surface: np.ndarray, normal, *,
                   tet_mask: np.ndarray | None = None,
                   surface_mask: np.ndarray | None = None) -> float:
    """Mean thickness ``T_mean = V / A_n`` (mm) of the (masked) breast along ``normal``.

    ``V`` is the volume of the selected tetrahedra and ``A_n`` the projected area of the
    selected outer triangles, ``1/2 sum |a_f . n|``.
    """
    x = np.asarray(points, float)
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    t = np.asarray(tets) if tet_mask is None else np.asarray(tets)[np.asarray(tet_mask, bool)]
    s = (np.asarray(surface) if surface_mask is None
         else np.asarray(surface)[np.asarray(surface_mask, bool)])
    p = x[t]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]),
                           p[:, 3] - p[:, 0])).sum() / 6.0
    q = x[s]
    av = 0.5 * np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    area = 0.5 * np.abs(av @ n).sum()
    if not area > 0:
        raise ResultCheckError("compression: the surface has no projected area along the plate "
                               "normal; check the model's outer triangles")
    return float(vol / area)
