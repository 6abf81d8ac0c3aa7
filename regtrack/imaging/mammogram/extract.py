"""Compose segmentation, contour, nipple and tumour into a :class:`regtrack.views.MammogramView`.

Frames: the canonical full-resolution pixel ``(row, col)`` has its centre at
``(x, y) = (col * s_col, row * s_row)`` mm, so ``x`` runs from the chest-wall edge to
the nipple and ``y`` downwards (medial for CC, infero-medial for MLO).  The view's
``image`` and ``breast_mask`` are on the segmentation's working grid (about 0.5 mm);
its ``origin`` and ``pixel_spacing`` place that grid in the same mm frame, so contours
keep full-resolution accuracy while the stored image stays small.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from regtrack.errors import MammogramError
from regtrack.views import MammogramView

from .config import MammogramConfig
from .contour import open_contour, polygon_area, smooth_polyline
from .dicom import MammogramImage
from .nipple import detect_nipple
from .segment import segment_breast
from .tumour import mask_to_contours, polygons_to_canonical, tumour_from_seed

log = logging.getLogger(__name__)


def _px_to_mm(rc: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    rc = np.asarray(rc, float)
    return np.stack([rc[..., 1] * spacing[1], rc[..., 0] * spacing[0]], -1)


def _pectoral_line_mm(pect: dict, seg, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Chest-wall line (point, anterior unit normal) in mm from the pectoral line."""
    a = _px_to_mm(seg.to_full_px([0.0, pect["x0_px"]]), spacing)  # on the top edge
    b = _px_to_mm(seg.to_full_px([pect["y0_px"], 0.0]), spacing)  # on the chest-wall edge
    t = (b - a) / np.linalg.norm(b - a)
    n = np.array([-t[1], t[0]])
    if n[0] < 0:
        n = -n
    return a, n, [a.tolist(), b.tolist()]


def _contour_distance(p: np.ndarray, poly: np.ndarray) -> float:
    from shapely.geometry import LineString, Point

    return float(LineString(poly).distance(Point(p)))


def extract_view(img: MammogramImage, *, tumour_polygon_px=None, tumour_mask=None,
                 tumour_seed_px=None, nipple_px=None,
                 config: MammogramConfig | None = None) -> MammogramView:
    """Extract breast contour, nipple and tumour contour(s) of a mammogram.

    Parameters
    ----------
    img : MammogramImage
        From :func:`read_mammogram` (canonical orientation).
    tumour_polygon_px : (K, 2) array or list of them, optional
        Tumour outline(s), (row, col) in the DICOM's own pixel grid.
    tumour_mask : 2-D bool, optional
        Tumour mask on the DICOM's own pixel grid (same shape as the stored image).
    tumour_seed_px : (2,) float, optional
        (row, col) of a point inside the tumour (DICOM grid): semi-automatic outline.
    nipple_px : (2,) float, optional
        (row, col) of the nipple (DICOM grid); detected when absent.
    config : MammogramConfig, optional
        Segmentation, contour and nipple parameters (defaults when None).

    Returns
    -------
    MammogramView
        Contours and nipple in mm of the canonical frame; ``meta`` records how each was
        obtained (segmentation figures, pectoral line, nipple confidence, orientation).
    """
    cfg = config or MammogramConfig()
    sp = np.asarray(img.pixel_spacing, float)
    try:
        seg = segment_breast(img.image, sp, view=img.view, config=cfg)
        band = max([b["width_mm"] + 1.0 for b in seg.removed.get("film_edge_bands", [])
                    if b["edge"] == "left"], default=0.0)
        skin_w, closed_w = open_contour(seg.mask, pectoral=seg.pectoral,
                                        chest_band_px=band / float(seg.spacing[1]))
    except MammogramError as err:
        raise MammogramError(f"{img.source}: {str(err).removeprefix('mammogram: ')}") from err
    skin = smooth_polyline(_px_to_mm(seg.to_full_px(skin_w), sp), sigma_mm=cfg.contour_sigma_mm)
    closed = _px_to_mm(seg.to_full_px(closed_w), sp)
    meta: dict = {"image": dict(img.meta), "segmentation": dict(seg.removed),
                  "config": dataclasses.asdict(cfg)}
    meta["segmentation"]["working_spacing_mm"] = seg.spacing.tolist()
    # area inside the closed boundary (skin line + chest-wall side), and inside the open
    # skin line closed by the straight chord between its ends
    meta["breast_area_mm2"] = abs(polygon_area(closed[:, ::-1]))
    meta["contour_chord_area_mm2"] = abs(polygon_area(skin[:, ::-1]))
    chest_wall = None
    if img.view == "MLO":
        if seg.pectoral is not None:
            p, n, seg_mm = _pectoral_line_mm(seg.pectoral, seg, sp)
            chest_wall = (p, n)
            meta["pectoral"] = {"line_mm": seg_mm, "contrast": seg.pectoral["contrast"],
                                "score": seg.pectoral["score"]}
        else:
            msg = "no pectoral muscle found on the MLO view; chest wall taken as the image edge"
            log.warning("%s: %s", img.source, msg)
            meta["pectoral"] = None
            meta.setdefault("notes", []).append(msg)
    meta["chest_wall"] = ("pectoral line" if chest_wall is not None else "image edge x = 0")

    if nipple_px is not None:
        rc = img.to_canonical_px(np.asarray(nipple_px, float))
        h, w = img.image.shape
        if not (0 <= rc[0] <= h - 1 and 0 <= rc[1] <= w - 1):
            raise MammogramError(f"{img.source}: nipple_px {list(nipple_px)} lies outside the "
                                 f"image ({img.orientation.source_shape[0]}x"
                                 f"{img.orientation.source_shape[1]} px); give [row, col] in "
                                 "the DICOM grid")
        nipple = _px_to_mm(rc, sp)
        dist = _contour_distance(nipple, skin)
        meta["nipple"] = {"method": "given (nipple_px)", "confidence": 1.0,
                          "distance_to_contour_mm": dist}
        if dist > 10.0:
            log.warning("%s: the given nipple is %.1f mm from the breast contour", img.source, dist)
    else:
        nipple, info = detect_nipple(skin, chest_wall=chest_wall, delta_mm=cfg.nipple_delta_mm)
        meta["nipple"] = info
    tumours: list[np.ndarray] = []
    if tumour_polygon_px is not None:
        polys = polygons_to_canonical(tumour_polygon_px, img.to_canonical_px)
        meta["tumour"] = {"method": "polygon"}
        tumours += polys
    if tumour_mask is not None:
        m = np.asarray(tumour_mask, bool)
        if m.shape != tuple(img.orientation.source_shape):
            raise MammogramError(f"{img.source}: tumour mask shape {m.shape} differs from the "
                                 f"image {tuple(img.orientation.source_shape)}; draw it on the "
                                 "DICOM grid")
        cs = mask_to_contours(img.orientation.apply(m))
        if not cs:
            raise MammogramError(f"{img.source}: the tumour mask is empty")
        meta["tumour"] = {"method": "mask"}
        tumours += cs
    if tumour_seed_px is not None:
        rc = img.to_canonical_px(np.asarray(tumour_seed_px, float))
        c, info = tumour_from_seed(img.image, sp, rc, roi_mm=cfg.seed_roi_mm)
        meta["tumour"] = info
        tumours.append(c)
    tumours_mm = [_px_to_mm(c, sp) for c in tumours]
    origin = _px_to_mm(seg.to_full_px([0.0, 0.0]), sp)
    meta["closed_boundary_points"] = int(len(closed))
    return MammogramView(view=img.view, laterality=img.laterality, breast_contour=skin,
                         nipple=np.asarray(nipple, float), tumour_contours=tumours_mm,
                         image=seg.small, pixel_spacing=seg.spacing.copy(), origin=origin,
                         breast_mask=seg.mask, source=img.source, meta=meta)
