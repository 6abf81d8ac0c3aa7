"""Assemble the phantom: labels (detailed Pelicano convention), a T1-like MRI and the truth."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy import ndimage

from regtrack.errors import ConfigError
from regtrack.imaging.volume import ImageVolume, LabelVolume
from regtrack.phantom import geometry as geo
from regtrack.phantom.params import PhantomParams

log = logging.getLogger(__name__)

MUSCLE, SKIN, BACKGROUND = -1, -2, 0
GLAND_LABELS = (1, 2, 3)  # most glandular first
TRANSITION = 4
FAT_LABELS = (5, 6, 7)  # least fatty first
#: fraction of the parenchyma labelled "transition" (4), between gland and fat
TRANSITION_FRACTION = 0.08

#: T1-weighted (no fat suppression) mean intensities, arbitrary units; fat is brightest.
T1_INTENSITY = {
    "air": 0.0, "thorax": 200.0, MUSCLE: 450.0, SKIN: 900.0, -3: 550.0, -4: 600.0,
    1: 650.0, 2: 750.0, 3: 850.0, TRANSITION: 1050.0, 5: 1300.0, 6: 1400.0, 7: 1500.0,
}


def _texture(shape, spacing, scale_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian random field with correlation length ``scale_mm``, unit variance."""
    f = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32),
                                sigma=scale_mm / np.asarray(spacing), mode="wrap")
    return (f - f.mean()) / (f.std() + 1e-12)


def _glandularity(u, a, v, texture, depth, p: PhantomParams) -> tuple[np.ndarray, np.ndarray]:
    """Glandularity score ``g`` and the mask where gland is allowed.

    ``g = T + 1.2 (1 - d^2)`` with ``T`` the texture field and ``d`` the normalised distance
    to the gland centre (on the mound axis at 45 % of the projection), so the fibroglandular
    tissue forms a textured cone behind the nipple, as in real breasts.  Gland is not
    allowed within ``gland_free_margin_mm`` of the skin, within 3 mm of the chest wall, or
    outside the mound (subcutaneous and retromammary fat).
    """
    ru, rv, pr = p.base_width_mm / 2, p.base_height_mm / 2, p.projection_mm
    d2 = ((u / (0.55 * ru)) ** 2 + ((v - geo.centreline_v(a, p)) / (0.55 * rv)) ** 2
          + ((a - 0.45 * pr) / (0.5 * pr)) ** 2)
    g = texture + 1.2 * (1.0 - d2)
    allowed = (depth > p.skin_thickness_mm + p.gland_free_margin_mm) & (a > 3.0) & geo.breast_mound(u, a, v, p)
    return g.astype(np.float32), allowed


def _tertile_labels(score: np.ndarray, labels3: tuple[int, int, int]) -> np.ndarray:
    """``labels3[0]`` for the top third of ``score``, ``labels3[1]`` the middle, ``[2]`` the rest."""
    n = score.size
    ranks = np.empty(n, np.int64)
    ranks[np.argsort(-score, kind="stable")] = np.arange(n)
    return np.asarray(labels3, np.int8)[np.minimum(3 * ranks // max(n, 1), 2)]


def _assign_parenchyma(labels, parenchyma, allowed, g, texture, gland_fraction: float) -> None:
    """Gland 1..3 (top ``gland_fraction`` of g where allowed), transition 4, fat 5..7.

    The gland and fat classes are split in thirds: by g for the gland (1 = most glandular),
    by the texture for the fat (5 = least fatty).
    """
    n = int(parenchyma.sum())
    cand = parenchyma & allowed
    gvals = g[cand]
    n_gland = min(int(round(gland_fraction * n)), gvals.size)
    n_trans = min(int(round(TRANSITION_FRACTION * n)), gvals.size - n_gland)
    sorted_g = np.sort(gvals)[::-1]
    gland = np.zeros_like(parenchyma)
    trans = np.zeros_like(parenchyma)
    if n_gland:
        gland = cand & (g >= sorted_g[n_gland - 1])
    if n_trans:
        trans = cand & ~gland & (g >= sorted_g[n_gland + n_trans - 1])
    fat = parenchyma & ~gland & ~trans
    labels[gland] = _tertile_labels(g[gland], GLAND_LABELS)
    labels[trans] = TRANSITION
    labels[fat] = _tertile_labels(texture[fat], FAT_LABELS)


def make_labels(p: PhantomParams) -> tuple[LabelVolume, dict]:
    """Label map (detailed Pelicano convention) and the internal masks used for the MRI."""
    problems = p.problems()
    if problems:
        raise ConfigError("phantom: " + "; ".join(problems))
    rng = np.random.default_rng(p.seed)
    grid = geo.make_grid(p)
    u, a, v = geo.local_coords(grid, p)
    full = np.ones(grid.shape, bool)
    muscle = full & (a < 0) & (a >= -p.muscle_thickness_mm)
    mound = geo.breast_mound(u, a, v, p)
    nip = geo.nipple(u, a, v, p) & ~mound
    chest_fat = full & (a >= 0) & (a < p.chest_fat_mm)
    body = muscle | mound | nip | chest_fat
    air = ~body & (a >= 0)
    depth = geo.skin_depth(body, air, grid)
    skin = body & (depth <= p.skin_thickness_mm) | nip
    parenchyma = (mound | chest_fat) & ~skin & ~muscle

    labels = np.zeros(grid.shape, np.int8)
    labels[muscle] = MUSCLE
    labels[skin] = SKIN
    texture = _texture(grid.shape, grid.spacing, p.texture_scale_mm, rng)
    g, allowed = _glandularity(u, a, v, texture, depth, p)
    _assign_parenchyma(labels, parenchyma, allowed, g, texture, p.gland_fraction)

    tumour = geo.tumour_mask(grid, p, rng)
    inner = parenchyma & mound & (depth > p.skin_thickness_mm + 1.0) & (a > 1.0)
    geo.check_tumour_inside(tumour, inner, p)
    labels[tumour] = p.tumour_label
    vol = LabelVolume(labels, grid.affine, None, {"generator": "regtrack.phantom", "seed": p.seed})
    masks = {"air": air, "thorax": ~body & ~air, "mound": mound | nip, "tumour": tumour, "grid": grid}
    return vol, masks


def make_mri(labels: LabelVolume, masks: dict, p: PhantomParams) -> ImageVolume:
    """T1-like MRI: class intensities, partial-volume blur, smooth bias, Rician noise.

    ``I = |(μ(label) * G_σ) · (1 + β b(x)) + n_1 + i n_2|``, ``n_i ~ N(0, σ_n)``, rounded to
    integers in [0, 4095] (12-bit, as scanners store).
    """
    rng = np.random.default_rng(p.seed + 7919)
    mu = np.zeros(labels.shape, np.float32)
    for lab, val in T1_INTENSITY.items():
        if isinstance(lab, int):
            mu[labels.data == lab] = val
    mu[masks["thorax"]] = T1_INTENSITY["thorax"]
    sp = np.asarray(p.spacing_mm)
    mu = ndimage.gaussian_filter(mu, sigma=0.35 / sp * np.array([1.0, 1.0, 1.0]) + 0.3)
    x, y, z = (np.linspace(-1, 1, n, dtype=np.float32) for n in labels.shape)
    bias = 1.0 + p.bias_amplitude * (0.6 * x[:, None, None] - 0.8 * y[None, :, None] + 0.3 * z[None, None, :] ** 2)
    s = mu * bias
    if p.noise_sd > 0:
        n1 = rng.standard_normal(labels.shape, dtype=np.float32) * p.noise_sd
        n2 = rng.standard_normal(labels.shape, dtype=np.float32) * p.noise_sd
        s = np.sqrt((s + n1) ** 2 + n2**2)
    img = np.clip(np.round(s), 0, 4095).astype(np.float32)
    return ImageVolume(img, labels.affine.copy(), None, {"generator": "regtrack.phantom", "weighting": "T1"})


def phantom_truth(labels: LabelVolume, masks: dict, p: PhantomParams) -> dict:
    """Ground truth: tumour centroid/extent/volume, nipple, volumes (LPS mm, mm^3)."""
    vv = labels.voxel_volume
    tum = labels.data == p.tumour_label
    idx = np.argwhere(tum)
    pts = labels.index_to_world(idx)
    sp = labels.spacing
    extent = pts.max(0) - pts.min(0) + sp  # voxel-face to voxel-face
    half = np.asarray(p.tumour_size_mm) / 2
    counts = {int(k): int(c) for k, c in zip(*np.unique(labels.data, return_counts=True))}
    parenchyma = np.isin(labels.data, GLAND_LABELS + (TRANSITION,) + FAT_LABELS) & masks["mound"]
    gland = np.isin(labels.data, GLAND_LABELS) & masks["mound"]
    return {
        "generator": "regtrack.phantom.make_phantom",
        "params": dataclasses.asdict(p),
        "frame": "LPS, mm",
        "nipple_lps_mm": geo.local_to_lps(geo.nipple_tip_local(p), p).tolist(),
        "chest_wall_plane": {"axis": "P", "lps_y_mm": float(p.base_centre[1]),
                             "note": "anterior surface of the muscle (label -1); breast is at y < this"},
        "base_centre_lps_mm": list(p.base_centre),
        "tumour_label": p.tumour_label,
        "tumour_centroid_lps_mm": pts.mean(0).tolist(),
        "tumour_centre_requested_lps_mm": geo.local_to_lps(np.asarray(p.tumour_offset_mm), p).tolist(),
        "tumour_extent_lps_mm": extent.tolist(),
        "tumour_volume_mm3": float(tum.sum() * vv),
        "tumour_volume_ellipsoid_mm3": float(4 / 3 * np.pi * half.prod()),
        "breast_mound_volume_mm3": float(masks["mound"].sum() * vv),
        "breast_mound_volume_analytic_mm3": geo.mound_volume_mm3(p),
        "gland_fraction_of_mound_parenchyma": float(gland.sum() / max(parenchyma.sum(), 1)),
        "label_voxel_counts": counts,
        "voxel_volume_mm3": vv,
        "shape": list(labels.shape),
        "spacing_mm": sp.tolist(),
    }


def make_phantom(params: PhantomParams | None = None) -> tuple[ImageVolume, LabelVolume, dict]:
    """Seeded prone breast phantom: ``(mri, labels, truth)``.

    Parameters
    ----------
    params
        :class:`PhantomParams` (defaults: the paper-like 25 x 22 x 25 mm tumour in a
        right breast at 0.66 x 0.66 x 1.4 mm).

    Returns
    -------
    mri : ImageVolume
        T1-like intensities (0..4095) on the label grid.
    labels : LabelVolume
        -3/-4 tumour, -2 skin (incl. nipple), -1 muscle, 0 background, 1-3 gland,
        4 transition, 5-7 fat (detailed Pelicano convention).
    truth : dict
        See :func:`phantom_truth`.  The same ``params`` always give identical arrays.
    """
    p = params or PhantomParams()
    labels, masks = make_labels(p)
    mri = make_mri(labels, masks, p)
    truth = phantom_truth(labels, masks, p)
    log.info("phantom: grid %s, tumour %.0f mm^3, mound %.0f mm^3", labels.shape,
             truth["tumour_volume_mm3"], truth["breast_mound_volume_mm3"])
    return mri, labels, truth
