"""From a (bilateral) label map to the voxel description of one breast.

Steps: reorient to LPS axes (:func:`~regtrack.model.select.reorient_lps`), split at the
midline, choose the side (named, else the one holding the tumour volume, else the larger
breast; the reason is logged and recorded), fit the chest-wall plane, keep the breast
voxels anterior of it (largest connected piece), crop with a margin and find the tumours.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from regtrack.errors import InputFileError
from regtrack.imaging.volume import LabelVolume
from regtrack.model.chestwall import ChestWall, Plane, find_chest_wall
from regtrack.model.config import MeshConfig
from regtrack.model.labels import LabelScheme
from regtrack.model.select import Midline, check_side, find_midline, reorient_lps, side_slices, unilateral_side
from regtrack.model.surfaces import plane_field
from regtrack.model.tumours import TumourSet, find_tumours

log = logging.getLogger(__name__)

WRONG_SIDE_MM = 30.0  # a one-breast map whose centroid is this far on the other side is refused


@dataclass
class PreparedBreast:
    """Voxel description of the chosen breast in a cropped, LPS-aligned label volume."""

    volume: LabelVolume  # cropped canonical labels (raw values)
    breast: np.ndarray  # bool: voxels of the model (after every cut)
    smooth_mask: np.ndarray  # bool: breast + body beyond the cut planes (for smoothing)
    inside: np.ndarray  # bool: voxel centres on the model side of every plane
    tumours: TumourSet
    planes: list[Plane]
    chest_wall: ChestWall
    side: str
    side_reason: str
    midline: Midline
    info: dict = field(default_factory=dict)


def _where(labels: LabelVolume) -> str:
    return str(labels.source) if labels.source is not None else "label map"


def _tumour_volume_by_side(tum: np.ndarray, data: np.ndarray, vv: float, mid: Midline,
                           min_mm3: float) -> dict[str, float]:
    out = {"R": 0.0, "L": 0.0}
    if not tum.any():
        return out
    sl = ndimage.find_objects(tum.astype(np.int8))[0]
    ts = find_tumours(tum[sl], data[sl], voxel_volume=vv, min_volume_mm3=min_mm3, quiet=True)
    for t in ts.kept:
        i = t.centroid_index[0] + sl[0].start
        side = "R" if (not mid.bilateral or i < mid.index) else "L"
        out[side] += t.volume_mm3
    return out


def choose_side(side: str | None, *, vol: LabelVolume, body: np.ndarray, mid: Midline,
                tumour_mm3: dict[str, float]) -> tuple[str, str]:
    """Return ``(side, reason)``; raise :class:`InputFileError` for an impossible side."""
    where = _where(vol)
    if not mid.bilateral:
        guess, cx = unilateral_side(vol, body)
        if side is None:
            return guess, f"one breast in the map; its centroid lies at LPS x = {cx:.0f} mm (patient {'left' if guess == 'L' else 'right'})"
        if side != guess and abs(cx) > WRONG_SIDE_MM:
            raise InputFileError(
                f"{where}: side = '{side}' asked, but the map holds one breast on the patient's "
                f"{'left' if guess == 'L' else 'right'} (centroid at LPS x = {cx:.0f} mm); set [mri] side = '{guess}'")
        return side, "named in the input (one breast in the map)"
    if side is not None:
        other = "L" if side == "R" else "R"
        if tumour_mm3[side] == 0 and tumour_mm3[other] > 0:
            log.warning("side %s named, but it holds no tumour; the %s breast holds %.0f mm^3 of tumour",
                        side, other, tumour_mm3[other])
        return side, "named in the input"
    with_t = [s for s in ("R", "L") if tumour_mm3[s] > 0]
    if len(with_t) == 1:
        return with_t[0], f"the only breast holding a tumour ({tumour_mm3[with_t[0]]:.0f} mm^3)"
    if len(with_t) == 2:
        s = max(with_t, key=lambda k: tumour_mm3[k])
        reason = (f"both breasts hold tumours (R {tumour_mm3['R']:.0f} mm^3, L {tumour_mm3['L']:.0f} mm^3); "
                  f"chose the larger tumour volume; set [mri] side to choose")
        log.warning("%s", reason)
        return s, reason
    counts = {s: int(body[side_slices(body.shape, mid, s)].sum()) for s in ("R", "L")}
    s = max(counts, key=counts.get)
    reason = "no tumour in either breast; chose the larger breast; set [mri] side to choose"
    log.warning("%s", reason)
    return s, reason


def _fov_planes(comp_bbox: tuple[slice, ...], shape: tuple[int, ...], vol: LabelVolume) -> list[Plane]:
    """Planes where the breast touches the field of view (the body continues beyond)."""
    planes = []
    d = vol.direction
    for a in range(3):
        for lo in (True, False):
            touches = comp_bbox[a].start == 0 if lo else comp_bbox[a].stop == shape[a]
            if not touches:
                continue
            idx = np.zeros(3)
            idx[a] = -0.5 if lo else shape[a] - 0.5
            n = d[:, a] if lo else -d[:, a]
            planes.append(Plane(n.copy(), float(n @ vol.index_to_world(idx)), "fov"))
    return planes


def _fold_cuts(cand: np.ndarray, dist: np.ndarray, sub: LabelVolume,
               fraction: float) -> tuple[list[Plane], np.ndarray]:
    """Axial cuts at the breast's cranial and caudal ends (inframammary fold).

    ``P(k)`` is the largest protrusion (mm) anterior of the chest-wall plane in axial slice
    ``k``.  From the apex slice, walking caudally (and cranially), the first slice with
    ``P < fraction * P_max`` ends the breast: when the body continues beyond it for more
    than 15 mm (upper abdomen, chest layer; a shorter taper is the breast's own end), it
    is cut by an axial plane half a voxel from that slice.
    """
    prof = np.where(cand, dist, -np.inf).max(axis=(0, 1))
    kpk = int(np.argmax(prof))
    thr = fraction * prof[kpk]
    below = np.nonzero(prof[:kpk] < thr)[0]
    above = np.nonzero(prof[kpk:] < thr)[0]
    planes = []
    up = sub.direction[:, 2]
    tail_vox = max(1, int(round(15.0 / float(sub.spacing[2]))))  # a taper shorter than 15 mm is the breast's own end
    if len(below) and np.count_nonzero(np.isfinite(prof[: int(below[-1]) + 1]) & (prof[: int(below[-1]) + 1] > 0)) > tail_vox:
        k0 = int(below[-1])
        cand = cand.copy()
        cand[:, :, : k0 + 1] = False
        planes.append(Plane(up.copy(), float(up @ sub.index_to_world([0, 0, k0 + 0.5])), "caudal"))
    if len(above) and np.count_nonzero(np.isfinite(prof[kpk + int(above[0]):]) & (prof[kpk + int(above[0]):] > 0)) > tail_vox:
        k1 = kpk + int(above[0])
        cand = cand.copy()
        cand[:, :, k1:] = False
        planes.append(Plane(-up, float(-up @ sub.index_to_world([0, 0, k1 - 0.5])), "cranial"))
    return planes, cand


def uncut_volumes(tumours: TumourSet, tum_half: np.ndarray, sl: tuple[slice, ...], vv: float) -> list[float]:
    """Voxel volume (mm^3) of each kept tumour before the chest-wall/fold/midline cuts.

    The whole tumour of kept tumour ``t`` is the union of the 26-connected components of
    the uncut tumour mask of the chosen half (``tum_half``, full array) that overlap ``t``
    (``sl``: the crop's position in the full array).
    """
    if not tumours.kept:
        return []
    lab, _ = ndimage.label(tum_half, structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(lab.ravel())
    sub = lab[sl]
    out = []
    for t in tumours.kept:
        comps = np.unique(sub[tumours.labelled == t.component])
        comps = comps[comps > 0]
        out.append(float(sizes[comps].sum() * vv))
    return out


def prepare_breast(labels: LabelVolume, *, scheme: LabelScheme, config: MeshConfig,
                   side: str | None = None) -> PreparedBreast:
    """Select, cut and crop one breast of ``labels`` (see the module docstring)."""
    where = _where(labels)
    side = check_side(side)
    vol = reorient_lps(labels)
    data = vol.data
    body = scheme.mask(data, "body")
    if not body.any():
        raise InputFileError(f"{where}: no voxel holds a breast label (tissue/skin/tumour values "
                             f"{sorted(scheme.body)}); check [mri] scheme or [mri.label_values]")
    muscle = scheme.mask(data, "muscle")
    tum = scheme.mask(data, "tumour")
    vv = vol.voxel_volume
    if not tum.any():
        log.warning("%s: no tumour label (%s) present; the model has no tumour region",
                    where, sorted(scheme.tumour))
    mid = find_midline(body, vol.spacing, min_prominence_mm=config.min_breast_prominence_mm)
    tvol = _tumour_volume_by_side(tum, data, vv, mid, config.min_tumour_volume_mm3)
    side, reason = choose_side(side, vol=vol, body=body, mid=mid, tumour_mm3=tvol)
    log.info("breast %s: %s", side, reason)
    hs = side_slices(vol.shape, mid, side)
    half = np.zeros(vol.shape[0], bool)
    half[hs] = True
    body_h = body & half[:, None, None]
    if not body_h.any():
        raise InputFileError(f"{where}: no breast tissue on side '{side}'; set [mri] side to the other breast")
    cw = find_chest_wall(vol, body_h, muscle & half[:, None, None], percentile=config.chest_wall_percentile,
                         offset_mm=config.chest_wall_offset_mm, tilt_max_deg=config.chest_wall_tilt_max_deg)
    bb = ndimage.find_objects(body_h.astype(np.int8))[0]
    sub = vol.crop([s.start for s in bb], [s.stop for s in bb])
    dist = plane_field(sub.shape, sub.affine, cw.plane, 1.0)
    cand = body_h[bb] & (dist > 0)
    cc_planes, cand = _fold_cuts(cand, dist, sub, config.fold_fraction)
    lab, n = ndimage.label(cand)
    if n == 0:
        raise InputFileError(f"{where}: nothing of the {side} breast lies anterior of the chest wall; "
                             "check the muscle label value or chest_wall_offset_mm")
    sizes = ndimage.sum_labels(cand, lab, np.arange(1, n + 1))
    keep = int(np.argmax(sizes)) + 1
    dropped = float(sizes.sum() - sizes[keep - 1]) * vv
    if dropped > 0:
        log.info("dropped %.0f mm^3 of body in %d piece(s) detached from the breast", dropped, n - 1)
    comp_sub = lab == keep
    cb = ndimage.find_objects(comp_sub.astype(np.int8))[0]
    comp_bbox = tuple(slice(s.start + o.start, s.stop + o.start) for s, o in zip(cb, bb))
    planes = [cw.plane] + _fov_planes(comp_bbox, vol.shape, vol) + cc_planes
    if mid.bilateral:
        n0 = vol.direction[:, 0] * (1.0 if side == "L" else -1.0)
        planes.append(Plane(n0, float(n0 @ vol.index_to_world([mid.index - 0.5, 0, 0])), "midline"))
    pad = np.ceil((config.margin_mm + 3.0 * config.smoothing_mm) / vol.spacing).astype(int) + 2
    lo = np.array([s.start for s in comp_bbox]) - pad
    hi = np.array([s.stop for s in comp_bbox]) + pad
    crop = vol.crop(lo, hi)
    lo_c = np.maximum(lo, 0)
    sl = tuple(slice(a, b) for a, b in zip(lo_c, np.minimum(hi, vol.shape)))
    breast = np.zeros(crop.shape, bool)
    breast[tuple(slice(c.start - l, c.stop - l) for c, l in zip(comp_bbox, lo_c))] = comp_sub[cb]
    inside = np.ones(crop.shape, bool)
    for p in planes:
        inside &= plane_field(crop.shape, crop.affine, p, 1.0) > 0
    body_c = body[sl]
    smooth_mask = breast | (body_c & ~inside)
    tumours = find_tumours(tum[sl] & breast, crop.data, voxel_volume=vv,
                           min_volume_mm3=config.min_tumour_volume_mm3)
    uncut = uncut_volumes(tumours, tum & half[:, None, None], sl, vv)
    kept_info = [{**t.to_dict(), "uncut_volume_mm3": round(u, 3), "cut_fraction": round(1.0 - t.volume_mm3 / u, 4) if u else 0.0}
                 for t, u in zip(tumours.kept, uncut)]
    for t, u in zip(tumours.kept, uncut):
        if u > t.volume_mm3 * 1.001:
            log.info("tumour %d: %.0f of its %.0f mm^3 lie beyond the cut planes (chest wall, folds, midline); "
                     "the model keeps %.0f mm^3", t.id, u - t.volume_mm3, u, t.volume_mm3)
    info = {
        "side": side, "side_reason": reason, "bilateral": mid.bilateral,
        "midline_index": mid.index, "breast_prominence_mm": mid.prominence_mm,
        "tumour_volume_by_side_mm3": tvol,
        "chest_wall": {**cw.plane.to_dict(), "source": cw.source, "n_columns": cw.n_points,
                       "tilt_deg": cw.tilt_deg, "fitted_normal_lps": cw.fitted_normal.tolist()},
        "cut_planes": [p.to_dict() for p in planes],
        "crop_lo_index": lo_c.tolist(), "crop_shape": list(crop.shape),
        "voxel_spacing_mm": vol.spacing.tolist(), "voxel_volume_mm3": vv,
        "breast_voxels": int(breast.sum()), "breast_voxel_volume_mm3": float(breast.sum() * vv),
        "detached_body_dropped_mm3": dropped,
        "tumours_kept": kept_info,
        "tumours_removed": [t.to_dict() for t in tumours.removed],
    }
    return PreparedBreast(crop, breast, smooth_mask, inside, tumours, planes, cw, side, reason, mid, info)
