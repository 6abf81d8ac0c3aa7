"""Simulated CC / MLO mammograms of a compressed phantom, with their exact annotations.

From the truth compression (:mod:`regtrack.phantom.truth_sim`) to a detector image:

1. *Projection.*  The deformed nodes are expressed in the plate frame
   (:func:`regtrack.virtual.project.default_frame`, the frame the pipeline's virtual
   mammogram uses), ``(X, Y, h)`` mm.
2. *Patient positioning.*  The in-plane rigid motion about the projected nipple ``n``

   .. math:: p' = R(\\theta)(p - n) + n + s, \\qquad R(\\theta) = \\begin{pmatrix}\\cos\\theta & -\\sin\\theta\\\\ \\sin\\theta & \\cos\\theta\\end{pmatrix}

   (the sense of :func:`regtrack.registration.geometry.rotation`, ``y`` down), so a
   pipeline that superimposes the nipples and rotates its virtual view by ``theta``
   about them recovers ``theta``.
3. *Detector.*  The canonical image (chest wall left, nipple right) has pixel
   ``(row, col)`` at ``(x, y) = (col, row) * pixel_mm`` with ``(x, y) = p' - o``.  Its
   left edge lies ``chest_cut_mm`` anterior of the most anterior chest-wall point, so
   the breast leaves the image along the chest-wall edge as on a real mammogram.
4. *X-ray physics.*  Path lengths ``L_g`` through fat, gland, transition and tumour
   tetrahedra (:func:`regtrack.virtual.xray.path_lengths`, rendered at ``render_mm`` and
   interpolated linearly to ``pixel_mm``: the path length is piecewise linear), plus a
   skin shell of thickness ``s`` on a rounded edge of radius ``R`` (half the plate gap):
   a ray at distance ``d`` inside the outline crosses
   ``L_skin = c_R(d) - c_{R-s}(d - s)`` mm of skin, ``c_r(d) = 2 sqrt(2 r d - d^2)``
   (``2 s`` where the breast is flat).  Line integral ``A = sum_g mu_g L_g``, detected
   quanta ``N ~ Poisson(I0 exp(-A))``, presentation value ``P = ln(I0 / N)`` mapped
   linearly to the stored range (dense = bright, MONOCHROME2).
5. *Annotations.*  The tumour outline (projected tumour, traced by
   :func:`regtrack.virtual.project.project_model`) and the projected nipple node, mapped
   with the same motion, in the DICOM's own pixel grid.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from regtrack.model.types import TUMOUR, BreastModel
from regtrack.phantom.dicom_mg import canonical_to_stored_rc, stored_from_canonical
from regtrack.phantom.make import GLAND_LABELS, TRANSITION
from regtrack.phantom.mammo_params import MammoTruthParams

log = logging.getLogger(__name__)

FAT, GLAND, TRANS, TUM = 0, 1, 2, 3


def rotation(theta_deg: float) -> np.ndarray:
    """``[[cos, -sin], [sin, cos]]`` (the registration's sense; y down = clockwise on screen)."""
    t = np.deg2rad(theta_deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


@dataclass(frozen=True)
class PlateToImage:
    """Rigid map from plate coordinates (mm) to canonical image mm: ``x = R (p - n) + n + s - o``."""

    theta_deg: float
    nipple_plate: np.ndarray  # n, mm
    shift: np.ndarray  # s, mm
    offset: np.ndarray  # o, mm: plate coordinates (after the motion) of the pixel (0, 0) centre

    def __call__(self, xy) -> np.ndarray:
        xy = np.asarray(xy, float)
        n = self.nipple_plate
        return (xy - n) @ rotation(self.theta_deg).T + n + self.shift - self.offset

    @property
    def translation(self) -> np.ndarray:
        """``t`` in ``x = R p + t`` (mm)."""
        n = self.nipple_plate
        return n - rotation(self.theta_deg) @ n + self.shift - self.offset

    def to_dict(self) -> dict:
        return {"formula": "x_canonical_mm = R(theta) (p_plate - n) + n + shift - offset = R p + translation",
                "theta_deg": self.theta_deg, "nipple_plate_mm": self.nipple_plate.tolist(),
                "shift_mm": self.shift.tolist(), "offset_mm": self.offset.tolist(),
                "translation_mm": self.translation.tolist()}


@dataclass
class SimulatedMammogram:
    """One simulated view: stored pixels, annotations (DICOM grid) and the truth."""

    view: str
    laterality: str
    stored: np.ndarray  # (rows, cols) uint16, stored (IHE) orientation
    spacing_mm: float
    nipple_rc: np.ndarray  # (2,) stored grid
    tumour_rc: np.ndarray  # (K, 2) stored grid
    truth: dict = field(default_factory=dict)
    canonical_a: np.ndarray | None = None  # noise-free line integral, canonical grid


def element_groups(model: BreastModel) -> np.ndarray:
    """Attenuation group per tet: 0 fat (and skin), 1 gland, 2 transition, 3 tumour."""
    g = np.zeros(model.n_tets, np.int64)
    lab = model.tissue_label
    if lab is not None:
        g[np.isin(lab, GLAND_LABELS)] = GLAND
        g[lab == TRANSITION] = TRANS
    g[model.region == TUMOUR] = TUM
    return g


def skin_path_mm(depth_mm: np.ndarray, *, radius_mm: float, skin_mm: float) -> np.ndarray:
    """Path length (mm) through a skin shell ``skin_mm`` thick on a rounded edge of radius
    ``radius_mm``, for rays ``depth_mm`` inside the projected outline (module docstring)."""
    d = np.clip(np.asarray(depth_mm, float), 0.0, None)
    r = max(float(radius_mm), skin_mm + 1e-6)

    def chord(rad, dd):
        dd = np.clip(dd, 0.0, rad)
        return 2.0 * np.sqrt(np.clip(2 * rad * dd - dd * dd, 0.0, None))

    inner = np.where(d > skin_mm, chord(r - skin_mm, d - skin_mm), 0.0)
    return np.maximum(chord(r, d) - inner, np.where(d >= r, 2.0 * skin_mm, 0.0))


def _detector(xy_moved: np.ndarray, xy_plain: np.ndarray, chest_moved: np.ndarray,
              p: MammoTruthParams) -> tuple[np.ndarray, tuple[int, int]]:
    """Offset ``o`` (plate mm of the pixel (0, 0) centre) and (rows, cols) of the image."""
    s = p.pixel_mm
    x0 = float(chest_moved[:, 0].max()) + p.chest_cut_mm + 0.5 * s
    both = np.concatenate([xy_moved, xy_plain])
    y0 = float(both[:, 1].min()) - p.margin_mm
    y1 = float(both[:, 1].max()) + p.margin_mm
    x1 = float(both[:, 0].max()) + p.margin_mm
    shape = (int(np.ceil((y1 - y0) / s)) + 1, int(np.ceil((x1 - x0) / s)) + 1)
    return np.array([x0, y0]), shape


def render_line_integral(local_img: np.ndarray, model: BreastModel, shape: tuple[int, int],
                         p: MammoTruthParams, *, gap_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free line integral ``A`` on the canonical grid, and the breast mask.

    ``local_img`` holds (x, y, h): canonical image mm and height above the lower plate.
    """
    from regtrack.virtual.raster import Grid
    from regtrack.virtual.xray import path_lengths

    k = max(1, int(round(p.render_mm / p.pixel_mm)))
    rs = k * p.pixel_mm
    coarse = Grid((0.0, 0.0), rs, (int(np.ceil(shape[0] / k)) + 1, int(np.ceil(shape[1] / k)) + 1))
    lengths = path_lengths(local_img, model.tets, element_groups(model), coarse)
    mu = {FAT: p.mu_fat_per_mm, GLAND: p.mu_gland_per_mm,
          TRANS: 0.5 * (p.mu_fat_per_mm + p.mu_gland_per_mm), TUM: p.mu_tumour_per_mm}
    a_c = sum(mu[g] * L for g, L in lengths.items())
    t_c = sum(lengths.values())
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64) / k
    a = ndimage.map_coordinates(a_c, [rr, cc], order=1, mode="nearest")
    t = ndimage.map_coordinates(t_c, [rr, cc], order=1, mode="nearest")
    mask = t > 1e-6
    # depth below the skin outline; the image's left edge cuts the breast (no skin there)
    depth = ndimage.distance_transform_edt(np.pad(mask, ((0, 0), (1, 0)), constant_values=True),
                                           sampling=p.pixel_mm)[:, 1:]
    a = a + p.mu_skin_excess_per_mm * skin_path_mm(depth, radius_mm=0.5 * gap_mm,
                                                    skin_mm=p.skin_mm) * mask
    return a, mask


def detector_image(a: np.ndarray, mask: np.ndarray, p: MammoTruthParams,
                   rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Quantum noise and presentation mapping: stored values in ``[0, 2**bits - 1]``."""
    top = 2 ** p.bits_stored - 1
    n = rng.poisson(p.quanta_per_pixel * np.exp(-a))
    pres = np.log(p.quanta_per_pixel / np.maximum(n, 0.5))
    a_ref = 1.1 * float(np.percentile(a[mask], 99.9)) if mask.any() else 1.0
    stored = np.clip(np.round(pres / a_ref * top), 0, top).astype(np.uint16)
    return stored, {"I0_quanta_per_pixel": p.quanta_per_pixel, "A_ref": a_ref,
                    "stored_value": f"round(ln(I0/N) / A_ref * {top})",
                    "A_max": float(a.max()), "bits_stored": p.bits_stored}


def _polygon_centroid(xy: np.ndarray) -> np.ndarray:
    from shapely.geometry import Polygon

    c = Polygon(xy).centroid
    return np.array([c.x, c.y])


def simulate_mammogram(model: BreastModel, positions: np.ndarray, view: str, p: MammoTruthParams, *,
                       plate_angle_deg: float | None = None, gap_mm: float = 50.0,
                       rng: np.random.Generator | None = None) -> SimulatedMammogram:
    """Render one view of a compressed model with its exact annotations.

    Parameters
    ----------
    model : BreastModel
    positions : (N, 3) float
        Deformed nodes (mm, model frame).
    view : {"CC", "MLO"}
    p : MammoTruthParams
        Positioning (rotation, shift), detector and physics settings.
    plate_angle_deg : float, optional
        Plate angle of the simulation (default: the view's nominal angle).
    gap_mm : float
        Plate gap (mm): twice the radius of the skin-line edge model.
    rng : numpy Generator
        Detector noise (default: seeded from ``p.seed`` and the view).
    """
    from regtrack.virtual.config import VirtualConfig
    from regtrack.virtual.project import default_frame, project_model

    v = view.upper()
    side = model.frame.side
    rng = rng or np.random.default_rng([p.seed, 0 if v == "CC" else 1])
    frame = default_frame(positions, v, side, angle_deg=plate_angle_deg)
    vm = project_model(model, positions, view=v, frame=frame,
                       config=VirtualConfig(pixel_mm=p.pixel_mm, render=False), source_name=f"truth {v}")
    local = frame.to_local(positions)
    xy = local[:, :2]
    nip = xy[model.nipple].copy()
    moved = PlateToImage(p.rotation_deg(v), nip, np.asarray(p.shift_mm(v), float), np.zeros(2))
    xy_m = moved(xy)
    offset, shape = _detector(xy_m, xy, xy_m[model.fixed] if model.fixed.any() else xy_m, p)
    m = PlateToImage(moved.theta_deg, nip, moved.shift, offset)
    local_img = np.column_stack([m(xy), local[:, 2]])
    a, mask = render_line_integral(local_img, model, shape, p, gap_mm=gap_mm)
    canon_stored, det = detector_image(a, mask, p, rng)
    s = p.pixel_mm
    to_px = lambda xy_mm: np.asarray(xy_mm, float)[..., ::-1] / s  # noqa: E731  (x, y) mm -> (row, col)
    nipple_mm = m(nip)
    if not vm.view.tumour_contours:
        raise ValueError(f"truth {v}: the projected tumour has no outline")
    tum_plate = vm.view.tumour_contours[0]
    tum_mm = m(tum_plate)
    tum_vol_c = _tumour_volume_centroid(model, positions)
    tum_vol_mm = m(frame.to_local(tum_vol_c)[:2])
    stored = stored_from_canonical(canon_stored, side)
    nip_rc = canonical_to_stored_rc(to_px(nipple_mm), shape=shape, laterality=side)
    tum_rc = canonical_to_stored_rc(to_px(tum_mm), shape=shape, laterality=side)
    breast_mm = m(vm.view.breast_contour)
    truth = {
        "view": v, "laterality": side, "image_shape": list(shape), "pixel_mm": s,
        "rotation_deg": m.theta_deg, "shift_mm": m.shift.tolist(),
        "plate_to_canonical": m.to_dict(), "plate_frame": frame.to_dict(),
        "nipple": {"canonical_mm": nipple_mm.tolist(), "dicom_rc": nip_rc.tolist(),
                   "plate_mm": nip.tolist(), "model_node": int(model.nipple)},
        "tumour": {"centroid_canonical_mm": _polygon_centroid(tum_mm).tolist(),
                   "centroid_dicom_rc": canonical_to_stored_rc(to_px(_polygon_centroid(tum_mm)),
                                                                shape=shape, laterality=side).tolist(),
                   "centroid_plate_mm": _polygon_centroid(tum_plate).tolist(),
                   "volume_centroid_projected_canonical_mm": tum_vol_mm.tolist(),
                   "area_mm2": float(abs(_shoelace(tum_mm))), "outline_points": int(len(tum_mm))},
        "breast": {"centroid_canonical_mm": _polygon_centroid(breast_mm).tolist(),
                   "mask_area_mm2": float(mask.sum() * s * s)},
        "detector": det,
    }
    log.info("simulated %s%s: %dx%d px, nipple (%.1f, %.1f) mm, tumour centroid (%.1f, %.1f) mm",
             side, v, shape[0], shape[1], *nipple_mm, *truth["tumour"]["centroid_canonical_mm"])
    return SimulatedMammogram(v, side, stored, s, nip_rc, tum_rc, truth, canonical_a=a)


def _shoelace(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _tumour_volume_centroid(model: BreastModel, positions: np.ndarray) -> np.ndarray:
    """Volume centroid (mm, model frame) of the deformed tumour tetrahedra."""
    t = model.tets[model.region == TUMOUR]
    pts = positions[t]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]),
                           pts[:, 3] - pts[:, 0])) / 6.0
    return (pts.mean(axis=1) * vol[:, None]).sum(0) / vol.sum()
