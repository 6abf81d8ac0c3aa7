"""Virtual mammogram of a deformed breast model (Lapuebla-Ferri et al., section 2.4).

The deformed nodes are projected orthogonally on the lower (receptor) plate, as in the
paper (or through a point source, optional).  The projected surface triangles of the
whole mesh and of each tumour are rasterised on a grid of ``pixel_mm`` pixels; the outer
boundary of each region is traced by marching squares (within half a pixel of the true
projected outline).  The breast contour is then opened by cutting off the points that lie
on the projection of the chest-wall faces (the posterior cut of the model: boundary faces
that are not skin), leaving the skin line from one chest-wall end to the other, as on a
real mammogram.  All outputs are in mm in the canonical 2-D frame of
:mod:`regtrack.views` via :func:`regtrack.virtual.frames.plate_frame`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from regtrack.errors import ResultCheckError
from regtrack.model.types import TUMOUR, BreastModel
from regtrack.views import MammogramView
from regtrack.virtual import contours as C
from regtrack.virtual import xray
from regtrack.virtual.config import VirtualConfig
from regtrack.virtual.frames import PlateFrame, plate_frame
from regtrack.virtual.raster import Grid, grid_around, rasterise
from regtrack.virtual.surface import boundary_faces

log = logging.getLogger(__name__)


@dataclass
class VirtualMammogram:
    """A virtual mammogram: the 2-D view plus the fields it was made from.

    Attributes
    ----------
    view : MammogramView
        Open breast contour, tumour contours, nipple and X-ray-like image (mm).
    closed_contour : (M, 2) float
        Full outline of the projected breast, chest-wall side included (mm).
    grid : Grid
        Pixel grid of ``view.image`` and ``view.breast_mask``.
    frame : PlateFrame
        Plate frame used for the projection.
    line_integral : (H, W) float or None
        ``A = sum_g mu_g L_g`` (dimensionless).
    path_lengths : dict
        ``{region: (H, W) path length (mm)}`` (1 tissue, 2 tumour).
    source : xray.PointSource or None
        Point source when the projection is magnified.
    """

    view: MammogramView
    closed_contour: np.ndarray
    grid: Grid
    frame: PlateFrame
    line_integral: np.ndarray | None = None
    path_lengths: dict = field(default_factory=dict)
    source: xray.PointSource | None = None


def default_frame(positions: np.ndarray, view: str, side: str, *,
                  angle_deg: float | None = None) -> PlateFrame:
    """Plate frame whose lower plate touches the lowest deformed node.

    The origin ``min_i(p_i . n) n`` keeps (X, Y) relative to the model origin (the
    undeformed nipple) while ``h = 0`` on the lowest point.
    """
    f = plate_frame(view, side, angle_deg=angle_deg)
    hmin = float(np.min(np.asarray(positions, float) @ f.normal))
    return f.with_origin(hmin * f.normal)


def _chest_wall_faces(model: BreastModel, faces: np.ndarray) -> tuple[np.ndarray, str]:
    """Boundary faces that are not skin (the posterior cut); how they were found."""
    if len(model.skin):
        skin = {tuple(f) for f in np.sort(model.skin, 1).tolist()}
        keep = np.array([tuple(f) not in skin for f in np.sort(faces, 1).tolist()])
        if keep.any():
            return faces[keep], "boundary faces that are not skin"
    keep = model.fixed[faces].all(1)
    return faces[keep], "boundary faces with three fixed (chest-wall) nodes"


def _tumour_ids(model: BreastModel) -> np.ndarray:
    sel = model.region == TUMOUR
    ids = model.tumour_id.copy()
    ids[sel & (ids <= 0)] = 1
    ids[~sel] = 0
    return ids


def _point_source(cfg: VirtualConfig, local: np.ndarray, model: BreastModel) -> xray.PointSource | None:
    """Source above the middle of the chest-wall edge (the central ray of a mammography unit)."""
    if cfg.source_to_image_mm <= 0:
        return None
    base = local[model.fixed] if model.fixed.any() else local
    foot = (float(base[:, 0].min()), float(0.5 * (base[:, 1].min() + base[:, 1].max())))
    src = xray.PointSource(foot, cfg.source_to_image_mm, -cfg.detector_gap_mm)
    if local[:, 2].max() >= src.height - 1.0:
        raise ResultCheckError(
            f"[virtual] source_to_image_mm = {cfg.source_to_image_mm}: the source is inside the "
            f"breast ({local[:, 2].max():.1f} mm thick); use a larger distance (about 650 mm)")
    return src


def project_model(model: BreastModel, positions: np.ndarray | None = None, *, view: str,
                  config: VirtualConfig | None = None, frame: PlateFrame | None = None,
                  source_name: str = "virtual") -> VirtualMammogram:
    """Virtual mammogram of ``model`` deformed to ``positions``.

    Parameters
    ----------
    model : BreastModel
    positions : (N, 3) float, optional
        Deformed node positions (mm, model frame) = points + displacement; default the
        undeformed points.
    view : {"CC", "MLO"}
    config : VirtualConfig, optional
    frame : PlateFrame, optional
        Plate frame of the simulation; default :func:`default_frame` (nominal angle).
    source_name : str
        Provenance written into the view.

    Returns
    -------
    VirtualMammogram

    Raises
    ------
    ResultCheckError
        Non-finite positions, a projection with no area, or no skin line left after the
        chest-wall side is removed.
    """
    cfg = config or VirtualConfig()
    pos = model.points if positions is None else np.asarray(positions, float)
    if pos.shape != model.points.shape or not np.isfinite(pos).all():
        raise ResultCheckError(
            f"{source_name}: deformed positions must be finite with shape {model.points.shape} "
            f"(got {pos.shape}); check the result's 'displacement' point data")
    side = model.frame.side
    frame = frame or default_frame(pos, view, side)
    local = frame.to_local(pos)
    source = _point_source(cfg, local, model)
    xy = xray.projected_xy(local, source)
    grid = grid_around(xy, spacing=cfg.pixel_mm, margin=cfg.margin_px)
    meta: dict = {"plate_frame": frame.to_dict(), "pixel_mm": cfg.pixel_mm, "fallbacks": []}

    faces = boundary_faces(model.tets, pos)
    mask = rasterise(xy, faces, grid)[0] > 0
    outlines = C.mask_contours(mask, grid)
    if not outlines:
        raise ResultCheckError(f"{source_name}: the projected breast has no area on the "
                               f"{frame.view} plate; check the deformed positions")
    if len(outlines) > 1:
        log.warning("%s: projection has %d separate parts; the largest is the breast",
                    source_name, len(outlines))
    closed = outlines[0]

    cw_faces, how = _chest_wall_faces(model, faces)
    samples = np.concatenate([
        C.sample_triangle_edges(xy, cw_faces, step=0.5 * cfg.pixel_mm),
        _mask_points(rasterise(xy, cw_faces, grid)[0] > 0, grid)])
    if len(samples) == 0:
        msg = ("no chest-wall faces found (model without non-skin boundary faces or fixed "
               f"nodes): the posterior {cfg.chest_wall_tol_mm} mm of the outline was cut instead")
        log.warning("%s: %s", source_name, msg)
        meta["fallbacks"].append(msg)
        flags = closed[:, 0] <= closed[:, 0].min() + cfg.chest_wall_tol_mm
    else:
        flags = C.chest_wall_flags(closed, samples, tol=cfg.chest_wall_tol_mm)
    breast = C.open_contour(closed, flags)
    if len(breast) < 3:
        raise ResultCheckError(f"{source_name}: no skin line left on the {frame.view} "
                               "projection after removing the chest-wall side; check the model's "
                               "'fixed' nodes and skin triangles")
    meta.update(chest_wall_from=how, chest_wall_ends_mm=[breast[0].tolist(), breast[-1].tolist()])

    tumours, ids = [], _tumour_ids(model)
    for k in np.unique(ids[ids > 0]):
        tmask = rasterise(xy, boundary_faces(model.tets[ids == k], pos), grid)[0] > 0
        tc = C.mask_contours(tmask, grid)
        if not tc:
            log.warning("%s: tumour %d is smaller than a %.2f mm pixel; not outlined",
                        source_name, k, cfg.pixel_mm)
            meta["fallbacks"].append(f"tumour {k} smaller than one pixel: no contour")
            continue
        tumours.append(tc[0])
    meta["tumour_ids"] = [int(k) for k in np.unique(ids[ids > 0])]

    vm = VirtualMammogram(MammogramView(frame.view, side, breast, xy[model.nipple].copy(),
                                        tumours, pixel_spacing=np.array([grid.spacing] * 2),
                                        origin=np.array(grid.origin), breast_mask=mask,
                                        source=source_name, meta=meta),
                          closed, grid, frame, source=source)
    if source is not None:
        meta["point_source"] = {"foot_mm": list(source.foot), "sid_mm": source.sid,
                                "detector_h_mm": source.detector_h}
    if cfg.render:
        _render_into(vm, model, local, cfg)
    return vm


def _mask_points(mask: np.ndarray, grid: Grid) -> np.ndarray:
    r, c = np.nonzero(mask)
    return np.stack([grid.origin[0] + c * grid.spacing, grid.origin[1] + r * grid.spacing], 1)


def _render_into(vm: VirtualMammogram, model: BreastModel, local: np.ndarray,
                 cfg: VirtualConfig) -> None:
    groups = np.where(model.region == TUMOUR, TUMOUR, 1)
    lengths = xray.path_lengths(local, model.tets, groups, vm.grid, source=vm.source)
    a, img = xray.render(lengths, {1: cfg.mu_tissue_per_mm, TUMOUR: cfg.mu_tumour_per_mm})
    vm.path_lengths, vm.line_integral, vm.view.image = lengths, a, img
    thick = sum(lengths.values())
    vm.view.meta["max_path_mm"] = float(thick.max())
    vm.view.meta["max_line_integral"] = float(a.max())
