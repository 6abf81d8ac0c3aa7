"""Synthetic mammograms with known geometry, and a minimal DICOM MG writer.

Used by the tests (known-answer checks of segmentation, contour, nipple, pectoral line
and orientation) and handy for demos.  The breast is a half ellipse on the chest-wall
(left) edge of the canonical frame,

.. math::  \\left(\\frac{x}{a}\\right)^2 + \\left(\\frac{y - y_c}{b}\\right)^2 \\le 1,
           \\quad x \\ge 0,

so its area is :math:`\\pi a b / 2` and its nipple (farthest point from the chest wall)
is :math:`(a, y_c)`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class SyntheticBreast:
    """A canonical synthetic mammogram and its ground truth (mm, canonical frame)."""

    image: np.ndarray
    spacing: tuple[float, float]
    a_mm: float
    b_mm: float
    yc_mm: float
    pectoral: tuple[float, float] | None = None  # (x0, y0) intercepts, mm
    label_box_px: tuple[int, int, int, int] | None = None  # r0, r1, c0, c1
    tumour: dict = field(default_factory=dict)

    @property
    def area_mm2(self) -> float:
        return float(np.pi * self.a_mm * self.b_mm / 2.0)

    @property
    def nipple_mm(self) -> np.ndarray:
        return np.array([self.a_mm, self.yc_mm])


def synthetic_breast(*, shape=(600, 400), spacing=(0.25, 0.25), a_mm=60.0, b_mm=50.0,
                     yc_mm=75.0, pectoral_mm: tuple[float, float] | None = None,
                     label: bool = True, film_edge_mm: float = 1.5,
                     tumour_mm: tuple[float, float, float] | None = None,
                     seed: int = 0) -> SyntheticBreast:
    """Canonical synthetic mammogram (values in [0, 1], chest wall on the left).

    Parameters
    ----------
    shape : (rows, cols)
    spacing : (row, col) mm
    a_mm, b_mm, yc_mm : float
        Half-ellipse semi-axes (anterior, vertical) and centre row (mm).
    pectoral_mm : (x0, y0), optional
        Bright muscle triangle ``x/x0 + y/y0 <= 1`` (mm) inside the breast (MLO).
    label : bool
        Burn a bright text-like block ("L" shape strokes) into the top-right background.
    film_edge_mm : float
        Width of bright film-edge strips along the right and top borders (0: none).
    tumour_mm : (x, y, radius), optional
        A brighter disk (blurred by 1 mm) inside the breast.
    """
    from scipy import ndimage as ndi

    rng = np.random.default_rng(seed)
    h, w = shape
    sy, sx = spacing
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    x, y = xx * sx, yy * sy
    breast = (x / a_mm) ** 2 + ((y - yc_mm) / b_mm) ** 2 <= 1.0
    img = np.full(shape, 0.02)
    texture = ndi.gaussian_filter(rng.normal(size=shape), 4.0)
    texture /= np.abs(texture).max()
    img[breast] = 0.45 + 0.1 * texture[breast]
    if pectoral_mm is not None:
        x0, y0 = pectoral_mm
        img[(x / x0 + y / y0 <= 1.0) & breast] = 0.8
    tum = {}
    if tumour_mm is not None:
        tx, ty, tr = tumour_mm
        disk = ((x - tx) ** 2 + (y - ty) ** 2 <= tr ** 2).astype(float)
        img += 0.25 * ndi.gaussian_filter(disk, 1.0 / np.array(spacing))
        tum = {"x": tx, "y": ty, "r": tr}
    box = None
    if label:
        r0, c0 = int(0.08 * h), int(0.75 * w)
        r1, c1 = r0 + int(12 / sy), c0 + int(8 / sx)
        stroke = int(round(1.0 / sx))
        img[r0:r1, c0:c0 + stroke] = 0.95
        img[r1 - stroke:r1, c0:c1] = 0.95
        box = (r0, r1, c0, c1)
    if film_edge_mm > 0:
        k = max(1, int(round(film_edge_mm / sx)))
        img[:, w - k:] = 0.9
        img[:k, :] = 0.9
    img += rng.normal(scale=0.005, size=shape)
    return SyntheticBreast(image=np.clip(img, 0, 1), spacing=(sy, sx), a_mm=a_mm, b_mm=b_mm,
                           yc_mm=yc_mm, pectoral=pectoral_mm, label_box_px=box, tumour=tum)


def write_dicom(path: str | os.PathLike, pixels: np.ndarray, *, modality: str = "MG",
                photometric: str = "MONOCHROME2", rle: bool = False, **tags) -> Path:
    """Write a minimal single-frame DICOM (Digital Mammography X-Ray Image Storage).

    ``pixels`` is stored as uint16; ``tags`` are set by keyword (e.g.
    ``ImageLaterality="L"``, ``ViewPosition="CC"``, ``PixelSpacing=[0.1, 0.1]``,
    ``PatientOrientation=["A", "R"]``).  ``rle`` compresses with RLE Lossless.  A given
    ``SOPInstanceUID`` is also the file meta's (else a random one: byte-exact files, e.g.
    for offsets into the header, need a fixed one).
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, RLELossless, generate_uid

    arr = np.asarray(pixels)
    if arr.dtype != np.uint16:
        arr = np.clip(np.round(arr), 0, 65535).astype(np.uint16)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1.2"
    meta.MediaStorageSOPInstanceUID = tags.pop("SOPInstanceUID", None) or generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = modality
    ds.PatientID = "synthetic"
    ds.Rows, ds.Columns = arr.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 0
    ds.PixelData = arr.tobytes()
    for k, v in tags.items():
        setattr(ds, k, v)
    if rle:
        ds.compress(RLELossless)
    path = Path(path)
    from regtrack._io import atomic_path

    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
    return path
