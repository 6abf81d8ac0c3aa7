"""Case folders: ``case.toml`` -> validated :class:`Case` (see ``docs/case-format.md``).

>>> from regtrack.case import load_case
>>> case = load_case("sample_cases/phantom01")          # doctest: +SKIP
>>> case.mri.labels, case.views["CC"].mammogram          # doctest: +SKIP
"""

from regtrack.case.annotations import read_tumour_mask, read_tumour_polygons
from regtrack.case.configs import Configs, resolve_configs
from regtrack.case.loader import CASE_FILE, find_case_file, load_case
from regtrack.case.overrides import SECTIONS, config_class
from regtrack.case.schema import (
    Case,
    LabelMapInfo,
    MammogramInfo,
    MriInput,
    Overrides,
    ViewInput,
)
from regtrack.case.summary import format_summary

__all__ = [
    "CASE_FILE",
    "SECTIONS",
    "Case",
    "Configs",
    "LabelMapInfo",
    "MammogramInfo",
    "MriInput",
    "Overrides",
    "ViewInput",
    "config_class",
    "find_case_file",
    "format_summary",
    "load_case",
    "read_tumour_mask",
    "read_tumour_polygons",
    "resolve_configs",
]
