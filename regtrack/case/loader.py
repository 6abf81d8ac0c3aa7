"""Load and validate a case folder: :func:`load_case`.

Validation collects *every* problem before failing, so a user fixes a case in one go.
Each problem is one line naming the file, the ``[section] key`` and the fix.  Unknown
keys are warnings naming the closest valid key; wrong types and missing required keys
are problems.  Validation never writes anything.
"""

from __future__ import annotations

import logging
import os
import re
import tomllib
from pathlib import Path

from regtrack.case._paths import resolve_inside
from regtrack.case.overrides import check_protocol_files, parse_overrides
from regtrack.case.schema import (
    LABEL_SUFFIXES,
    MASK_SUFFIXES,
    Case,
    CaseTable,
    LabelMapInfo,
    MammogramInfo,
    MriInput,
    MriTable,
    Overrides,
    ViewInput,
    ViewTable,
)
from regtrack.config import closest_key, parse_section
from regtrack.errors import CaseError
from regtrack.model.labels import LabelScheme, get_scheme, scheme_from_table
from regtrack.views import VIEWS

log = logging.getLogger(__name__)

CASE_FILE = "case.toml"
TOP_LEVEL = ("case", "mri", "views", "model", "mechanics", "contact", "protocol", "registration")
_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class _Findings:
    """Problems and warnings collected while validating."""

    def __init__(self) -> None:
        self.problems: list[str] = []
        self.warnings: list[str] = []

    def add(self, problems: list[str], warnings: list[str] | None = None) -> None:
        self.problems += problems
        self.warnings += warnings or []


def find_case_file(path: str | os.PathLike) -> tuple[Path, str]:
    """``(absolute case.toml path, name to show in messages)`` for a folder or a file."""
    p = Path(path)
    toml = p / CASE_FILE if p.is_dir() else p
    if not toml.is_file():
        if p.is_dir():
            raise CaseError(f"{toml}: no {CASE_FILE} in the case folder; write one "
                            "(see docs/case-format.md)")
        raise CaseError(f"{p}: no such case folder or case file; give a folder holding "
                        f"{CASE_FILE} or the path of the {CASE_FILE} itself")
    return Path(os.path.abspath(toml)), str(toml)


def read_toml(toml: Path, where: str) -> dict:
    """Parse ``toml``; a syntax error becomes a :class:`CaseError` with the line."""
    try:
        return tomllib.loads(toml.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise CaseError(f"{where}: not UTF-8 text ({exc.reason}); save it as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(f"{where}: invalid TOML: {exc}; fix the syntax") from None


def _table(doc: dict, key: str, where: str, f: _Findings, *, required: bool) -> dict | None:
    value = doc.get(key)
    if value is None:
        if required:
            f.problems.append(f"{where} [{key}]: missing section; add a [{key}] table "
                              "(see docs/case-format.md)")
        return None
    if not isinstance(value, dict):
        f.problems.append(f"{where} {key} = {value!r}: expected a table [{key}]")
        return None
    return value


def _parse_case(doc: dict, where: str, f: _Findings) -> tuple[str, str]:
    table = _table(doc, "case", where, f, required=True)
    if table is None:
        return "", ""
    obj, p, w = parse_section(CaseTable, table, where=f"{where} [case]")
    f.add(p, w)
    if obj.id is None:
        if "id" not in table:
            f.problems.append(f'{where} [case] id: missing; add a pseudonymous id, e.g. '
                              'id = "case001" (never a patient name or number)')
    elif not _ID_RE.match(obj.id):
        f.problems.append(f"{where} [case] id = {obj.id!r}: use letters, digits, '.', '_' "
                          "and '-' only (it names output files)")
    return obj.id or "", obj.title


def _parse_scheme(mri: MriTable, where: str, f: _Findings) -> tuple[LabelScheme | None, str | None]:
    base = None
    if mri.scheme is not None:
        try:
            base = get_scheme(mri.scheme, where=f"{where} [mri] scheme")
        except CaseError as exc:
            f.problems += exc.problems
            return None, None
    if mri.label_values is None:
        if base is None:
            f.problems.append(f"{where} [mri] scheme: missing; set scheme = "
                              '"pelicano-simple" or "pelicano-detailed", or give '
                              "[mri.label_values]")
        return base, mri.scheme
    try:
        scheme = scheme_from_table(mri.label_values, base=base,
                                   where=f"{where} [mri.label_values]")
    except CaseError as exc:
        f.problems += exc.problems
        return None, None
    if not scheme.tumour:
        f.problems.append(f"{where} [mri.label_values] tumour: no tumour label values; list "
                          "them, e.g. tumour = [-3, -4]")
        return None, None
    return scheme, mri.scheme


def _parse_mri(doc: dict, root: Path, where: str, f: _Findings) -> MriInput | None:
    table = _table(doc, "mri", where, f, required=True)
    if table is None:
        return None
    mri, p, w = parse_section(MriTable, table, where=f"{where} [mri]")
    f.add(p, w)
    labels = None
    if mri.labels is None:
        if "labels" not in table:
            f.problems.append(f'{where} [mri] labels: missing; add labels = '
                              '"path/to/labels.nii.gz" (relative to the case folder)')
    else:
        labels, prob = resolve_inside(root, mri.labels, at=f"{where} [mri] labels",
                                      suffixes=LABEL_SUFFIXES)
        if prob:
            f.problems.append(prob)
    series = None
    if mri.series is not None:
        series, prob = resolve_inside(root, mri.series, at=f"{where} [mri] series", kind="dir")
        if prob:
            f.problems.append(prob)
    scheme, scheme_name = _parse_scheme(mri, where, f)
    if labels is None or scheme is None:
        return None
    nipple = tuple(mri.nipple_lps_mm) if mri.nipple_lps_mm and len(mri.nipple_lps_mm) == 3 else None
    explicit = tuple(k for k in (mri.label_values or {}) if isinstance(k, str))
    return MriInput(labels=labels, scheme=scheme, scheme_name=scheme_name, series=series,
                    side=mri.side, nipple_lps_mm=nipple,  # type: ignore[arg-type]
                    explicit_classes=explicit)


def _parse_view(name: str, table: dict, root: Path, where: str, f: _Findings) -> ViewInput | None:
    at = f"{where} [views.{name}]"
    v, p, w = parse_section(ViewTable, table, where=at)
    f.add(p, w)
    ok = not p
    paths: dict[str, Path | None] = {}
    for key, kind_suffixes in (("mammogram", None), ("tumour_polygon", (".json",)),
                               ("tumour_mask", MASK_SUFFIXES)):
        value = getattr(v, key)
        paths[key] = None
        if value is None:
            continue
        path, prob = resolve_inside(root, value, at=f"{at} {key}", suffixes=kind_suffixes)
        if prob:
            f.problems.append(prob)
            ok = False
        paths[key] = path
    if v.mammogram is None:
        if "mammogram" not in table:
            f.problems.append(f'{at} mammogram: missing; add mammogram = "path/to/{name.lower()}'
                              '.dcm" (relative to the case folder)')
        ok = False
    if v.tumour_polygon is not None and v.tumour_mask is not None:
        f.problems.append(f"{at}: both tumour_polygon and tumour_mask are given; keep one")
        ok = False
    elif v.tumour_polygon is None and v.tumour_mask is None:
        f.warnings.append(f"{at}: no tumour_polygon or tumour_mask; the {name} view runs in "
                          "tracking mode (registration on the breast outline and nipple, the "
                          "MRI lesion predicted on the mammogram; TS_Av, theta_p,t and d_T "
                          "are not computed)")
    if not ok:
        return None
    return ViewInput(name=name, mammogram=paths["mammogram"],  # type: ignore[arg-type]
                     tumour_polygon=paths["tumour_polygon"], tumour_mask=paths["tumour_mask"],
                     nipple_px=tuple(v.nipple_px) if v.nipple_px else None,  # type: ignore[arg-type]
                     pixel_spacing_mm=tuple(v.pixel_spacing_mm) if v.pixel_spacing_mm else None)  # type: ignore[arg-type]


def _parse_views(doc: dict, root: Path, where: str, f: _Findings) -> dict[str, ViewInput]:
    table = _table(doc, "views", where, f, required=False)
    if table is None:
        if "views" not in doc:
            f.warnings.append(f"{where} [views]: no mammograms given; only the MRI stages "
                              "(mesh, simulate, project) can run on this case")
        return {}
    out: dict[str, ViewInput] = {}
    for name, sub in table.items():
        if name not in VIEWS:
            near = closest_key(name.upper(), VIEWS) if name.upper() not in VIEWS else name.upper()
            f.problems.append(f"{where} [views.{name}]: unknown view '{name}'; valid views: "
                              + ", ".join(VIEWS) + (f" (did you mean '{near}'?)" if near else ""))
            continue
        if not isinstance(sub, dict):
            f.problems.append(f"{where} [views] {name} = {sub!r}: expected a table [views.{name}]")
            continue
        view = _parse_view(name, sub, root, where, f)
        if view is not None:
            out[name] = view
    return {k: out[k] for k in VIEWS if k in out}


def _check_top_level(doc: dict, where: str, f: _Findings) -> None:
    for key in doc:
        if key not in TOP_LEVEL:
            near = closest_key(key, TOP_LEVEL)
            f.warnings.append(f"{where}: unknown section or key '{key}' ignored"
                              + (f" (did you mean '{near}'?)" if near else ""))


def load_case(path: str | os.PathLike, *, deep: bool = True) -> Case:
    """Load, resolve and validate a case folder.

    Parameters
    ----------
    path : str or PathLike
        The case folder (holding ``case.toml``) or the ``case.toml`` file itself.
    deep : bool
        Also open the inputs cheaply: the label map (label values present, tumour
        present, nipple inside), each mammogram's DICOM header (readable, size, pixel
        spacing), the tumour polygon/mask and ``nipple_px`` (inside the image).

    Returns
    -------
    Case
        With :attr:`Case.warnings` (also logged) and, when ``deep``, the
        :attr:`Case.label_map` and :attr:`Case.mammograms` summaries.

    Raises
    ------
    CaseError
        Listing every problem found (``err.problems``); ``err.warnings`` holds the
        warnings found on the way.  Nothing is written in either case.
    """
    toml, where = find_case_file(path)
    root = toml.parent
    doc = read_toml(toml, where)
    f = _Findings()
    _check_top_level(doc, where, f)
    case_id, title = _parse_case(doc, where, f)
    mri = _parse_mri(doc, root, where, f)
    views = _parse_views(doc, root, where, f)
    parsed, p, w = parse_overrides(doc, where=where)
    f.add(p, w)
    f.add(check_protocol_files(parsed, root, where=where, deep=deep))
    overrides = {sec: Overrides(section=sec, target=_target(sec), table=tbl, config=cfg)
                 for sec, (tbl, cfg) in parsed.items()}
    label_map: LabelMapInfo | None = None
    mammograms: dict[str, MammogramInfo] = {}
    if deep:
        label_map, mammograms = _deep(mri, views, root, where, f)
    for w in f.warnings:
        log.warning(w)
    if f.problems:
        err = CaseError(f.problems)
        err.warnings = list(f.warnings)  # type: ignore[attr-defined]
        raise err
    assert mri is not None  # a missing [mri] is a problem above
    return Case(root=root, toml_path=toml, id=case_id, title=title, mri=mri, views=views,
                overrides=overrides, warnings=list(f.warnings), label_map=label_map,
                mammograms=mammograms, raw=doc, deep=deep)


def _target(section: str) -> str:
    from regtrack.case.overrides import SECTIONS

    return SECTIONS[section]


def _deep(mri: MriInput | None, views: dict[str, ViewInput], root: Path, where: str,
          f: _Findings) -> tuple[LabelMapInfo | None, dict[str, MammogramInfo]]:
    from regtrack.case.inputs import check_label_map, check_series
    from regtrack.case.mammo import check_lateralities, check_view

    label_map = None
    if mri is not None:
        label_map, p, w = check_label_map(mri, where=where, root=root)
        f.add(p, w)
        if mri.series is not None:
            p, w = check_series(mri.series, label_map, where=where, root=root)
            f.add(p, w)
    infos: dict[str, MammogramInfo] = {}
    for name, view in views.items():
        info, p, w = check_view(view, where=where, root=root)
        f.add(p, w)
        if info is not None:
            infos[name] = info
    side = mri.side if mri is not None else None
    f.add(*check_lateralities(infos, side, where=where))
    return label_map, infos
