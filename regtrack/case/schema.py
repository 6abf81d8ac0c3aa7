"""Typed contents of a case folder: :class:`Case`, :class:`MriInput`, :class:`ViewInput`.

``case.toml`` is parsed section by section into the ``*Table`` dataclasses below with
:func:`regtrack.config.parse_section` (types, choices, unknown keys), then turned into the
resolved, immutable :class:`Case` that every later stage receives.  All paths in a
:class:`Case` are absolute and lie inside :attr:`Case.root`.

Units: ``nipple_lps_mm`` in mm (DICOM patient frame, LPS); ``nipple_px`` and polygon
points in pixels ``(row, col)`` of the mammogram's own grid; ``pixel_spacing_mm`` in mm
(row spacing first, DICOM order).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from regtrack.config import param
from regtrack.model.labels import LabelScheme
from regtrack.views import LATERALITIES

#: Suffixes accepted for ``[mri] labels`` (lower case).
LABEL_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr", ".zip")
#: Suffixes accepted for ``tumour_mask``.
MASK_SUFFIXES = (".png", ".tif", ".tiff", ".bmp")


# --------------------------------------------------------------------------- raw tables
@dataclass(frozen=True)
class CaseTable:
    """``[case]``: identification."""

    id: str | None = param(None, "", "pseudonymous case id used in every output name "
                           "(letters, digits, '.', '_', '-'); required")
    title: str = param("", "", "free text shown in reports")


@dataclass(frozen=True)
class MriTable:
    """``[mri]``: the MRI label map and how to read it."""

    labels: str | None = param(None, "", "label map: NIfTI (.nii, .nii.gz), MetaImage "
                               "(.mha, .mhd), NRRD (.nrrd, .nhdr) or a .zip holding one .mha; "
                               "required")
    series: str | None = param(None, "", "optional DICOM MR series folder; its geometry "
                               "must match the label map")
    scheme: str | None = param(None, "", "label preset of regtrack.model.labels "
                               "('pelicano-simple', 'pelicano-detailed'); required unless "
                               "[mri.label_values] lists tissue and tumour")
    side: str | None = param(None, "", "breast to model; must match the mammograms' "
                             "laterality; default: chosen by the model stage",
                             choices=LATERALITIES)
    nipple_lps_mm: tuple[float, ...] | None = param(
        None, "mm", "explicit nipple point (L, P, S) in the label map's patient frame; "
        "default: detected on the skin surface")
    label_values: dict | None = param(None, "", "table overriding the preset per class "
                                      "(tissue, tumour, skin, muscle, background)")

    def problems(self) -> list[str]:
        if self.nipple_lps_mm is not None and len(self.nipple_lps_mm) != 3:
            return [f"nipple_lps_mm = {list(self.nipple_lps_mm)!r}: must have 3 values "
                    "[L, P, S] in mm"]
        return []


@dataclass(frozen=True)
class ViewTable:
    """``[views.CC]`` / ``[views.MLO]``: one mammogram and its annotations."""

    mammogram: str | None = param(None, "", "DICOM mammogram (MG, DX or CR); required")
    tumour_polygon: str | None = param(None, "", 'JSON {"points_rc": [[row, col], ...]} '
                                       'or {"polygons_rc": [[[row, col], ...], ...]} in '
                                       "the DICOM's own pixel grid")
    tumour_mask: str | None = param(None, "", "alternative to tumour_polygon: binary image "
                                    "(PNG/TIFF) on the DICOM's pixel grid, non-zero = tumour")
    nipple_px: tuple[float, ...] | None = param(None, "px", "nipple [row, col] in the "
                                                "DICOM's own pixel grid; default: detected")
    pixel_spacing_mm: tuple[float, ...] | None = param(
        None, "mm", "[row, col] pixel spacing; only for DICOMs without PixelSpacing / "
        "ImagerPixelSpacing (it then wins over the tags, with a warning)")

    def problems(self) -> list[str]:
        out = []
        if self.nipple_px is not None and len(self.nipple_px) != 2:
            out.append(f"nipple_px = {list(self.nipple_px)!r}: must have 2 values [row, col]")
        sp = self.pixel_spacing_mm
        if sp is not None and (len(sp) != 2 or min(sp) <= 0):
            out.append(f"pixel_spacing_mm = {list(sp)!r}: must be 2 positive values "
                       "[row_mm, col_mm]")
        return out


# --------------------------------------------------------------------------- resolved case
@dataclass(frozen=True)
class MriInput:
    """The MRI side of a case, paths resolved.

    Attributes
    ----------
    labels : Path
        Label map file (absolute, inside the case folder).
    scheme : LabelScheme
        Label value of each class (preset, possibly overridden by ``[mri.label_values]``).
    scheme_name : str or None
        Preset name, or None for a fully custom ``[mri.label_values]``.
    series : Path or None
        DICOM MR series folder.
    side : {"L", "R"} or None
        Breast to model.
    nipple_lps_mm : (3,) tuple of float or None
        Explicit nipple (LPS, mm).
    explicit_classes : tuple of str
        Classes listed in ``[mri.label_values]`` (their absent values are warned about).
    """

    labels: Path
    scheme: LabelScheme
    scheme_name: str | None = None
    series: Path | None = None
    side: str | None = None
    nipple_lps_mm: tuple[float, float, float] | None = None
    explicit_classes: tuple[str, ...] = ()


@dataclass(frozen=True)
class ViewInput:
    """One mammographic view of a case, paths resolved.

    Attributes
    ----------
    name : {"CC", "MLO"}
    mammogram : Path
        DICOM file.
    tumour_polygon, tumour_mask : Path or None
        At most one is set (see :func:`regtrack.case.annotations.read_tumour_polygons`).
    nipple_px : (2,) tuple of float or None
        ``(row, col)`` in the DICOM's pixel grid.
    pixel_spacing_mm : (2,) tuple of float or None
        User-given ``(row, col)`` spacing (mm).
    """

    name: str
    mammogram: Path
    tumour_polygon: Path | None = None
    tumour_mask: Path | None = None
    nipple_px: tuple[float, float] | None = None
    pixel_spacing_mm: tuple[float, float] | None = None


@dataclass(frozen=True)
class LabelMapInfo:
    """What deep validation learned from the label map (no voxel data kept)."""

    shape: tuple[int, int, int]
    spacing_mm: tuple[float, float, float]
    origin_lps_mm: tuple[float, float, float]
    counts: dict[int, int]  # label value -> voxel count
    affine: np.ndarray = field(default_factory=lambda: np.eye(4), compare=False)  # voxel -> LPS


@dataclass(frozen=True)
class MammogramInfo:
    """What deep validation learned from a mammogram's DICOM header."""

    rows: int
    columns: int
    spacing_mm: tuple[float, float] | None
    spacing_source: str  # "PixelSpacing", "ImagerPixelSpacing", "case.toml", or "none"
    modality: str = ""
    laterality: str = ""  # ImageLaterality / Laterality, "" when absent
    view_position: str = ""
    tumour_polygons: int = 0  # number of polygons (or mask components) found


@dataclass(frozen=True)
class Overrides:
    """One override section, e.g. ``[mechanics]`` or ``[protocol.CC]``.

    ``table`` is the TOML table as written; ``config`` the parsed config dataclass
    (defaults + overrides) or None while the owning stage's class does not exist.
    """

    section: str
    target: str  # "module:Class"
    table: dict
    config: Any = None


@dataclass(frozen=True)
class Case:
    """A validated case folder.

    Attributes
    ----------
    root : Path
        Case folder (absolute); every input path lies inside it.
    toml_path : Path
        The ``case.toml`` read.
    id, title : str
    mri : MriInput
    views : dict of str to ViewInput
        Keyed by view name (``"CC"``, ``"MLO"``), in :data:`regtrack.views.VIEWS` order.
    overrides : dict of str to Overrides
        Keyed by section name (``"model"``, ``"mechanics"``, ``"contact"``,
        ``"protocol.CC"``, ``"protocol.MLO"``, ``"registration"``); only sections that
        appear in ``case.toml``.
    warnings : list of str
        Non-fatal findings (unknown keys, absent optional labels, ...), one line each.
    label_map : LabelMapInfo or None
        Filled by deep validation.
    mammograms : dict of str to MammogramInfo
        Filled by deep validation.
    raw : dict
        The TOML document as read (for provenance in outputs).
    deep : bool
        Whether the inputs were opened and checked (``load_case(..., deep=True)``).
    """

    root: Path
    toml_path: Path
    id: str
    title: str
    mri: MriInput
    views: dict[str, ViewInput] = field(default_factory=dict)
    overrides: dict[str, Overrides] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    label_map: LabelMapInfo | None = None
    mammograms: dict[str, MammogramInfo] = field(default_factory=dict)
    raw: dict = field(default_factory=dict)
    deep: bool = False

    def override_table(self, section: str) -> dict:
        """The TOML table of ``section`` as written (empty when absent)."""
        ov = self.overrides.get(section)
        return dict(ov.table) if ov is not None else {}

    def config(self, section: str) -> Any:
        """The config dataclass of ``section`` with this case's overrides applied.

        Sections absent from ``case.toml`` give the class defaults.  Raises
        :class:`KeyError` for an unknown section.
        """
        from regtrack.case.overrides import config_class

        ov = self.overrides.get(section)
        if ov is not None and ov.config is not None:
            return ov.config
        return config_class(section)()

