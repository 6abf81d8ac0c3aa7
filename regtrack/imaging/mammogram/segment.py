"""Breast segmentation of a canonical mammogram (chest wall on the left).

Works on a block-averaged copy of the image at about ``working_spacing_mm``
(:class:`~regtrack.imaging.mammogram.config.MammogramConfig`, 0.5 mm by default) and
keeps the exact map back to full-resolution pixels: working pixel ``(i, j)``
is the mean of full pixels ``[i f_r, (i+1) f_r) x [j f_c, (j+1) f_c)``, so its centre is
the full-resolution point ``(i f_r + (f_r - 1)/2, j f_c + (f_c - 1)/2)``.

Steps (:func:`segment_breast`)
------------------------------
1. Smooth (Gaussian, sigma = ``smooth_mm``) and threshold at
   ``t = b + max(k_rel (f - b), k_noise * 1.4826 MAD_b)``, where ``b`` and ``f`` are the
   medians of the Otsu background and foreground classes and ``MAD_b`` the median
   absolute deviation of the background: a low threshold that keeps the faint skin
   line of film mammograms but stays above detector noise.
2. Morphological opening with a disk of radius ``open_mm``: burned-in text labels and
   the bright film-edge strips (both narrower than the disk) vanish or detach.
3. Keep the largest component touching the chest-wall (left) edge (or the largest one
   when none touches it): labels and markers lying in the background are dropped.
4. Restore the detail the opening rounded off (nipple tip, skin fringe) by adding back
   pixels of the unsmoothed block-averaged image above ``t`` within ``open_mm`` of that
   component (no outward bias from the blur), then fill holes.
5. Remove film-edge glow: scanned films are often brighter in a band a few mm wide
   along the film border (:func:`remove_border_strips`); where the mask is such a narrow
   band along a border over a long run, the band is cut off.
6. MLO: remove the pectoral muscle (:mod:`.pectoral`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from regtrack.errors import MammogramError

from .config import MammogramConfig

log = logging.getLogger(__name__)


@dataclass
class BreastSegmentation:
    """Breast mask on the working grid and how it was obtained.

    Attributes
    ----------
    mask : 2-D bool
        Breast (pectoral muscle excluded for MLO) on the working grid.
    tissue_mask : 2-D bool
        Everything attached to the chest wall, pectoral included.
    small : 2-D float32
        The block-averaged image on the working grid, values in [0, 1].
    factor : (2,) int
        Block size (rows, cols) in full-resolution pixels.
    spacing : (2,) float
        Working-grid spacing (row, col) in mm.
    threshold : float
        Foreground threshold (image units, [0, 1]).
    pectoral : dict or None
        Pectoral line (see :func:`regtrack.imaging.mammogram.pectoral.find_pectoral`).
    removed : dict
        Counts and areas (mm^2) of what was removed (labels, film edges).
    """

    mask: np.ndarray
    tissue_mask: np.ndarray
    small: np.ndarray
    factor: tuple[int, int]
    spacing: np.ndarray
    threshold: float
    pectoral: dict | None = None
    removed: dict = field(default_factory=dict)

    def to_full_px(self, rc) -> np.ndarray:
        """Map (..., 2) working-grid (row, col) to full-resolution canonical (row, col)."""
        rc = np.asarray(rc, float)
        f = np.asarray(self.factor, float)
        return rc * f + (f - 1.0) / 2.0


def block_average(image: np.ndarray, spacing,
                  working_spacing_mm: float) -> tuple[np.ndarray, tuple[int, int]]:
    """Block-average ``image`` to about ``working_spacing_mm`` (never upsamples).

    Rows/columns beyond the last whole block (fewer than one block) are dropped.
    """
    fr = max(1, int(round(working_spacing_mm / float(spacing[0]))))
    fc = max(1, int(round(working_spacing_mm / float(spacing[1]))))
    h, w = (image.shape[0] // fr) * fr, (image.shape[1] // fc) * fc
    if h < 3 * fr or w < 3 * fc:  # fewer than 3 x 3 working pixels: nothing to segment
        raise MammogramError(
            f"mammogram: {image.shape[0]}x{image.shape[1]} px at {float(spacing[0]):.4g} x "
            f"{float(spacing[1]):.4g} mm is under 3 x 3 blocks of {working_spacing_mm:g} mm; "
            "check the pixel spacing (PixelSpacing / pixel_spacing_mm)")
    small = image[:h, :w].reshape(h // fr, fr, w // fc, fc).mean(axis=(1, 3), dtype=np.float64)
    return small.astype(np.float32), (fr, fc)


def foreground_threshold(smooth: np.ndarray, *, k_rel: float = 0.05, k_noise: float = 6.0) -> float:
    """Low breast/background threshold (see module docstring, step 1)."""
    from skimage.filters import threshold_otsu

    v = smooth.ravel()
    t_otsu = float(threshold_otsu(v))
    bg, fg = v[v <= t_otsu], v[v > t_otsu]
    if fg.size == 0 or bg.size == 0:
        raise MammogramError("mammogram: the image is uniform; no breast to segment")
    b, f = float(np.median(bg)), float(np.median(fg))
    mad = float(np.median(np.abs(bg - b)))
    return b + max(k_rel * (f - b), k_noise * 1.4826 * mad)


def _disk(radius_px: float) -> np.ndarray:
    r = max(1, int(round(radius_px)))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    return (xx * xx + yy * yy) <= r * r


def _chest_component(opened: np.ndarray) -> np.ndarray:
    lab, n = ndi.label(opened)
    if n == 0:
        raise MammogramError("mammogram: no breast found (nothing brighter than the background)")
    areas = np.bincount(lab.ravel())
    areas[0] = 0
    left = np.unique(lab[:, 0])
    left = left[left > 0]
    # the breast touches the chest-wall edge; prefer such a component when it is large
    if left.size and areas[left].max() >= 0.2 * areas.max():
        keep = left[np.argmax(areas[left])]
    else:
        keep = int(np.argmax(areas))
    return lab == keep


def _depth_from_edge(mask: np.ndarray) -> np.ndarray:
    """Per row, the number of consecutive True pixels starting at column 0."""
    first_false = np.where(~mask.all(axis=1), np.argmin(mask, axis=1), mask.shape[1])
    return first_false


def remove_border_strips(mask: np.ndarray, spacing, *, strip_max_mm: float = 15.0,
                         min_run_mm: float = 15.0,
                         margin_mm: float = 1.0) -> tuple[np.ndarray, list]:
    """Cut narrow bands that run along an image border (film-edge glow, film margins).

    For each border, ``d[i]`` is how far the mask reaches into the image from the border
    along line ``i``.  Runs of at least ``min_run_mm`` consecutive lines with
    ``0 < d < strip_max_mm`` are bands; in them the mask is cleared up to
    ``min(d[i], w + margin_mm)``, with ``w`` the band's median depth, so breast tissue
    reaching beyond the band (where the breast meets the band) is kept.

    Returns the cleaned mask and a list of ``{"edge", "width_mm", "length_mm"}``.
    """
    out = mask.copy()
    found: list[dict] = []
    # (name, view of the mask with that border at column 0, spacing across, spacing along)
    edges = (("left", 0, False), ("right", 0, True), ("top", 1, False), ("bottom", 1, True))
    for name, k, flip in edges:
        m = out.T if k else out
        m = m[:, ::-1] if flip else m
        across, along = (spacing[0], spacing[1]) if k else (spacing[1], spacing[0])
        d = _depth_from_edge(m)
        cand = (d > 0) & (d * across < strip_max_mm)
        lab, n = ndi.label(cand)
        for j in range(1, n + 1):
            idx = np.nonzero(lab == j)[0]
            if idx.size * along < min_run_mm:
                continue
            w = float(np.median(d[idx]))
            cut = np.minimum(d[idx], int(np.ceil(w + margin_mm / across)))
            cols = np.arange(m.shape[1])
            m[idx[:, None], cols[None, :]] &= cols[None, :] >= cut[:, None]
            found.append({"edge": name, "width_mm": w * across, "length_mm": idx.size * along})
    return out, found


def segment_breast(image: np.ndarray, spacing, *, view: str,
                   config: MammogramConfig | None = None) -> BreastSegmentation:
    """Segment the breast of a canonical mammogram (values in [0, 1], chest wall left).

    Parameters
    ----------
    image : 2-D float
        Canonical image, bright = dense.
    spacing : (2,) float
        Pixel spacing (row, col) of ``image`` in mm.
    view : {"CC", "MLO"}
        The pectoral muscle is removed for MLO (``config.remove_pectoral``).
    config : MammogramConfig, optional
        Working spacing, smoothing, threshold, opening and film-edge parameters.
    """
    cfg = config or MammogramConfig()
    small, factor = block_average(image, spacing, cfg.working_spacing_mm)
    wsp = np.asarray(spacing, float) * np.asarray(factor, float)
    if min(small.shape) < 16:
        raise MammogramError(f"mammogram: image too small to segment ({image.shape} px)")
    smooth = ndi.gaussian_filter(small, sigma=cfg.smooth_mm / wsp)
    t = foreground_threshold(smooth, k_rel=cfg.threshold_rel, k_noise=cfg.threshold_noise)
    fg = smooth > t
    r_open = cfg.open_mm / float(wsp.min())
    opened = ndi.binary_opening(fg, structure=_disk(r_open))
    comp = _chest_component(opened)
    near = ndi.binary_dilation(comp, structure=_disk(r_open + 1))
    # add back on the unsmoothed (block-averaged) image: no outward bias from the blur
    tissue = ndi.binary_fill_holes((small > t) & near)
    # the add-back can join a few stray pixels: keep the component that holds comp
    lab, _ = ndi.label(tissue)
    ids = np.unique(lab[comp])
    tissue = np.isin(lab, ids[ids > 0])
    tissue, strips = remove_border_strips(tissue, wsp, strip_max_mm=cfg.strip_max_mm,
                                          min_run_mm=cfg.strip_min_run_mm)
    lab, n = ndi.label(tissue)
    if n == 0:
        raise MammogramError("mammogram: no breast left after removing the film-edge bands")
    if n > 1:
        areas = np.bincount(lab.ravel())
        areas[0] = 0
        tissue = lab == int(np.argmax(areas))
    px_area = float(wsp[0] * wsp[1])
    lab_fg, n_fg = ndi.label(fg)
    outside = np.unique(lab_fg[fg & ~tissue])
    removed = {
        "components_removed": int(np.count_nonzero(outside)),
        "area_removed_mm2": float(np.count_nonzero(fg & ~tissue) * px_area),
        "threshold": float(t),
        "open_radius_mm": cfg.open_mm,
        "film_edge_bands": strips,
    }
    log.debug("segmentation: threshold %.4f, %d foreground components removed (%.0f mm^2)",
              t, removed["components_removed"], removed["area_removed_mm2"])
    mask = tissue
    pect = None
    if view == "MLO" and cfg.remove_pectoral:
        from .pectoral import find_pectoral

        pect = find_pectoral(smooth, tissue, wsp, min_contrast=cfg.pectoral_min_contrast)
        if pect is not None:
            mask = tissue & ~pect.pop("mask")
            lab, n = ndi.label(mask)
            if n > 1:
                areas = np.bincount(lab.ravel())
                areas[0] = 0
                mask = lab == int(np.argmax(areas))
    return BreastSegmentation(mask=mask, tissue_mask=tissue, small=small, factor=factor,
                              spacing=wsp, threshold=float(t), pectoral=pect, removed=removed)


def chest_wall_side(image: np.ndarray, spacing) -> tuple[str, float]:
    """Which vertical image edge the breast rests on: ("left" | "right", confidence).

    The breast is the largest bright component after a 2 mm opening at ~1 mm; the chest
    wall is the edge it touches over the longer run.  The confidence is
    ``|l - r| / (l + r)`` of the two contact lengths.
    """
    small, factor = block_average(image, spacing, 1.0)
    wsp = np.asarray(spacing, float) * np.asarray(factor, float)
    smooth = ndi.gaussian_filter(small, sigma=1.0 / wsp)
    fg = smooth > foreground_threshold(smooth)
    opened = ndi.binary_opening(fg, structure=_disk(2.0 / float(wsp.min())))
    lab, n = ndi.label(opened)
    if n == 0:
        raise MammogramError("mammogram: no breast found (nothing brighter than the background)")
    areas = np.bincount(lab.ravel())
    areas[0] = 0
    big = lab == int(np.argmax(areas))
    band = max(1, int(round(3.0 / wsp[1])))
    left = float(np.count_nonzero(big[:, :band].any(axis=1)))
    right = float(np.count_nonzero(big[:, -band:].any(axis=1)))
    if left == right:
        cols = np.nonzero(big.any(axis=0))[0]
        centre = 0.5 * (cols.min() + cols.max())
        return ("left" if centre < big.shape[1] / 2 else "right"), 0.0
    return ("left" if left > right else "right"), abs(left - right) / (left + right)
