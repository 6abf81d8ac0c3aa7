"""Patient privacy: identifiers kept out of every output, de-identified DICOM.

Radiology inputs carry patient identifiers (DICOM PatientName, PatientID, birth date,
accession number, institution, ...).  regtrack never needs them, so by default none of
them reaches a report, a JSON/CSV file, a PNG, a PDF or a log line:

* :func:`collect_identifiers` reads the identifying attributes of the case's DICOM
  headers (mammograms and the MR series; headers only, no pixels) into an
  :class:`Identifiers` set;
* :meth:`Identifiers.scrub` / :meth:`Identifiers.scrub_obj` replace every occurrence of
  those values (and the case folder's absolute path, which often holds a patient name)
  in text and JSON-like objects; :func:`scrub_logs` does the same for every log record
  while a run is active;
* :func:`pseudonymous_id` makes sure the case id that names the outputs is not itself an
  identifier (a case folder named after the patient ID gets ``anon-<hash>`` instead);
* :func:`deidentify_dataset` applies the DICOM PS3.15 Annex E *Basic Application Level
  Confidentiality Profile* to the attributes regtrack sets in DICOM files it writes, and
  records the fact (PatientIdentityRemoved, DeidentificationMethod(CodeSequence)).

``regtrack run --keep-identifiers`` opts out: the identifiers are then written into
``provenance.json`` (``patient``) and nothing is scrubbed.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: DICOM attributes that identify the patient, the study or the site (keywords; the
#: PS3.15 Table E.1-1 attributes regtrack could plausibly meet in MG/MR headers).
IDENTIFYING_KEYWORDS: tuple[str, ...] = (
    "PatientName", "PatientID", "PatientBirthDate", "PatientBirthTime", "PatientBirthName",
    "OtherPatientIDs", "OtherPatientNames", "PatientMotherBirthName", "PatientAddress",
    "PatientTelephoneNumbers", "MedicalRecordLocator", "IssuerOfPatientID",
    "AccessionNumber", "StudyID", "InstitutionName", "InstitutionAddress",
    "InstitutionalDepartmentName", "ReferringPhysicianName", "PerformingPhysicianName",
    "NameOfPhysiciansReadingStudy", "PhysiciansOfRecord", "RequestingPhysician",
    "OperatorsName", "StationName", "DeviceSerialNumber", "PatientComments",
    "AdditionalPatientHistory", "Occupation", "MilitaryRank", "BranchOfService",
    "RegionOfResidence", "CountryOfResidence", "EthnicGroup",
)

#: Basic profile action for the attributes regtrack's writers set: "Z" = zero-length
#: (Type 2 attributes), "X" = remove, "D" = dummy value.  Every other identifying
#: attribute of :data:`IDENTIFYING_KEYWORDS` is removed.
BASIC_PROFILE_ACTIONS: dict[str, str] = {
    "PatientName": "D", "PatientID": "D", "PatientBirthDate": "Z", "PatientSex": "Z",
    "StudyDate": "Z", "StudyTime": "Z", "AccessionNumber": "Z", "ReferringPhysicianName": "Z",
    "StudyID": "Z", "SeriesDate": "X", "SeriesTime": "X", "ContentDate": "Z",
    "ContentTime": "Z", "AcquisitionDate": "X", "AcquisitionTime": "X",
    "AcquisitionDateTime": "X", "PatientAge": "X", "PatientWeight": "X", "PatientSize": "X",
}

#: DCM code of the profile (PS3.16 CID 7050)
BASIC_PROFILE_CODE = ("113100", "DCM", "Basic Application Confidentiality Profile")
DEIDENTIFICATION_METHOD = "regtrack: DICOM PS3.15 E.1 Basic Profile"  # LO: <= 64 chars

#: values that are placeholders, not identifiers (never scrubbed)
_PLACEHOLDERS = {"", "ANONYMOUS", "ANONYMIZED", "ANON", "UNKNOWN", "NONE", "N/A", "NA", "^", "1"}
_MIN_LEN = 3  # shorter values (e.g. "F", "12") would scrub innocent text


def _variants(keyword: str, value: str) -> set[str]:
    """The forms a value can take in text: PN components and orderings, ISO dates."""
    v = value.strip()
    out = {v}
    if "^" in v:  # person name: Family^Given^Middle^Prefix^Suffix
        parts = [p.strip() for p in v.split("^") if p.strip()]
        out |= set(parts)
        if len(parts) >= 2:
            fam, given = parts[0], parts[1]
            out |= {f"{given} {fam}", f"{fam} {given}", f"{fam}, {given}", f"{fam}_{given}",
                    f"{given}_{fam}", " ".join(parts)}
    if keyword.endswith("Date") and re.fullmatch(r"\d{8}", v):
        out |= {f"{v[:4]}-{v[4:6]}-{v[6:]}", f"{v[6:]}/{v[4:6]}/{v[:4]}", f"{v[4:6]}/{v[6:]}/{v[:4]}"}
    return {s for s in out if len(s) >= _MIN_LEN and s.upper() not in _PLACEHOLDERS}


def _values(elem_value: Any) -> list[str]:
    if elem_value is None:
        return []
    if isinstance(elem_value, (list, tuple)) or type(elem_value).__name__ == "MultiValue":
        return [str(v) for v in elem_value]
    return [str(elem_value)]


@dataclass
class Identifiers:
    """Identifying values found in a case's inputs, and the scrubbing they imply.

    Attributes
    ----------
    by_keyword : dict
        ``{keyword: [value, ...]}`` as read from the DICOM headers.
    values : set of str
        Every form to scrub (PN components, date formats, ...), at least 3 characters.
    paths : dict
        Absolute paths (the case folder) replaced by a neutral label.
    shown : dict
        The same paths as the user gave them on the command line: log records and
        progress lines (the user's own console) name the case's files this way, so a
        warning says ``cases/p01/mammo/mlo.dcm``, not ``<case>/mammo/mlo.dcm``; output
        files keep the neutral label.  Identifiers inside them are still redacted.
    """

    by_keyword: dict[str, list[str]] = field(default_factory=dict)
    values: set[str] = field(default_factory=set)
    paths: dict[str, str] = field(default_factory=dict)
    shown: dict[str, str] = field(default_factory=dict)

    REDACTED = "[redacted]"

    def add(self, keyword: str, value: str) -> None:
        for v in _values(value):
            forms = _variants(keyword, v)
            if forms:
                self.by_keyword.setdefault(keyword, [])
                if v not in self.by_keyword[keyword]:
                    self.by_keyword[keyword].append(v)
                self.values |= forms

    def _pattern(self) -> re.Pattern | None:
        if not self.values:
            return None
        alts = sorted(self.values, key=len, reverse=True)  # longest first
        return re.compile("|".join(re.escape(a) for a in alts), re.IGNORECASE)

    def scrub(self, text: str, *, console: bool = False) -> str:
        """``text`` with every identifier replaced by ``[redacted]`` and every recorded
        absolute path by its label (case-insensitive); ``console``: by the path as the
        user gave it (:attr:`shown`), for log records and progress lines."""
        for p, label in sorted(self.paths.items(), key=lambda kv: -len(kv[0])):
            text = text.replace(p, self.shown.get(p, label) if console else label)
        pat = self._pattern()
        return text if pat is None else pat.sub(self.REDACTED, text)

    def found_in(self, text: str) -> list[str]:
        """The identifier forms that occur in ``text`` (case-insensitive)."""
        low = text.lower()
        return sorted(v for v in self.values if v.lower() in low)

    def keywords_in(self, text: str) -> list[str]:
        """The DICOM keywords (``PatientName``, ...) whose values occur in ``text``; used to
        say *what kind* of identifier was removed without repeating it."""
        low = text.lower()
        return [kw for kw, vals in self.by_keyword.items()
                if any(f.lower() in low for v in vals for f in _variants(kw, v))]

    def redact(self, text: str, where: str) -> str:
        """:meth:`scrub` ``text`` and announce it: a warning names ``where`` and the kinds
        of identifier removed (never their values) when a DICOM identifier was found."""
        kws = self.keywords_in(text)
        if kws:
            log.warning("%s contains DICOM patient identifiers (%s); they are shown as %s in "
                        "every output (pass --keep-identifiers to keep them)", where,
                        ", ".join(kws), self.REDACTED)
        return self.scrub(text)

    def redact_obj(self, obj: Any, where: str) -> Any:
        """:meth:`scrub_obj` with one announcement, as :meth:`redact`, for the whole object."""
        import json

        kws = self.keywords_in(json.dumps(obj, default=str))
        if kws:
            log.warning("%s contains DICOM patient identifiers (%s); they are written as %s",
                        where, ", ".join(kws), self.REDACTED)
        return self.scrub_obj(obj)

    def scrub_obj(self, obj: Any) -> Any:
        """Copy of a JSON-like object (dict/list/tuple/str/...) with every string scrubbed."""
        if isinstance(obj, str):
            return self.scrub(obj)
        if isinstance(obj, Path):
            return self.scrub(str(obj))
        if isinstance(obj, dict):
            return {self.scrub(k) if isinstance(k, str) else k: self.scrub_obj(v)
                    for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return type(obj)(self.scrub_obj(v) for v in obj)
        return obj

    def __bool__(self) -> bool:
        return bool(self.values or self.paths)


def read_identifiers(path: str | os.PathLike, into: Identifiers | None = None) -> Identifiers:
    """Identifying values of one DICOM file's header (pixels are not read).

    Unreadable files contribute nothing (the readers report them on their own).
    """
    import pydicom

    ids = into if into is not None else Identifiers()
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True, force=True)
    except Exception as err:  # noqa: BLE001 - privacy scan must never fail a run
        log.debug("identifier scan skipped %s: %s", Path(path).name, type(err).__name__)
        return ids
    for kw in IDENTIFYING_KEYWORDS:
        try:
            value = ds.get(kw)
        except Exception:  # noqa: BLE001 - a corrupt element is not an identifier
            continue
        if value is not None and str(value).strip():
            ids.add(kw, value)
    return ids


def collect_identifiers(case: Any, *, max_series_files: int = 3) -> Identifiers:
    """Identifiers of a loaded :class:`regtrack.case.Case`: its mammograms' headers, the
    first files of its MR series, and its folder's absolute path (shown as ``<case>``)."""
    ids = Identifiers()
    for view in getattr(case, "views", {}).values():
        read_identifiers(view.mammogram, ids)
    series = getattr(getattr(case, "mri", None), "series", None)
    if series is not None and Path(series).is_dir():
        files = sorted(p for p in Path(series).iterdir() if p.is_file())[:max_series_files]
        for p in files:
            read_identifiers(p, ids)
    root = getattr(case, "root", None)
    if root is not None:
        ids.paths[str(Path(root).resolve())] = "<case>"
        ids.paths[os.path.abspath(root)] = "<case>"
    return ids


def identifiers_of_case_folder(path: str | os.PathLike) -> Identifiers:
    """Like :func:`collect_identifiers`, straight from a case folder (or its case.toml),
    *before* it is loaded: the loader's own log lines and warnings name the case's files,
    so the scrubbing must be in place first.  Paths are followed only inside the folder;
    an unreadable case.toml gives the folder paths alone (the loader reports it)."""
    import tomllib

    p = Path(path)
    toml = p / "case.toml" if p.is_dir() else p
    root = toml.parent
    ids = Identifiers()
    ids.paths[str(root.resolve())] = "<case>"
    ids.paths[os.path.abspath(root)] = "<case>"
    given = str(root)
    if len(given) >= 3 and given.strip("./"):
        ids.paths[given] = "<case>"
    for p in list(ids.paths):
        ids.shown[p] = given
    try:
        doc = tomllib.loads(toml.read_text(encoding="utf-8"))
    except Exception:  # noqa: BLE001 - the loader reports a bad case.toml
        return ids
    real_root = root.resolve()

    def inside(value: Any, *, folder: bool) -> Path | None:
        if not isinstance(value, str) or not value.strip() or os.path.isabs(value):
            return None
        q = (root / value).resolve()
        ok = q.is_relative_to(real_root) and (q.is_dir() if folder else q.is_file())
        return q if ok else None

    views = doc.get("views")
    for table in (views.values() if isinstance(views, dict) else []):
        q = inside(table.get("mammogram") if isinstance(table, dict) else None, folder=False)
        if q is not None:
            read_identifiers(q, ids)
    mri = doc.get("mri")
    series = inside(mri.get("series") if isinstance(mri, dict) else None, folder=True)
    if series is not None:
        for f in sorted(f for f in series.iterdir() if f.is_file())[:3]:
            read_identifiers(f, ids)
    return ids


def pseudonymous_id(case_id: str, ids: Identifiers) -> str:
    """``case_id``, or ``anon-<8 hex>`` when it contains a patient identifier.

    The replacement is a SHA-256 of the id, so the same case always gets the same
    pseudonym (outputs of repeated runs line up) while the id itself is not shown.
    """
    if not ids.found_in(case_id):
        return case_id
    pseudo = "anon-" + hashlib.sha256(case_id.encode()).hexdigest()[:8]
    log.warning("[case] id contains a DICOM patient identifier; outputs are named %s instead "
                "(give a pseudonymous id in case.toml, or pass --keep-identifiers)", pseudo)
    return pseudo


class ScrubFilter(logging.Filter):
    """Logging filter that scrubs identifiers from each record's final message."""

    def __init__(self, ids: Identifiers):
        super().__init__()
        self.ids = ids

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            msg = record.getMessage()
        except Exception:  # noqa: BLE001 - leave malformed records to logging
            return True
        clean = self.ids.scrub(msg, console=True)
        if clean != msg or record.args:
            record.msg, record.args = clean, None
        return True


@contextlib.contextmanager
def scrub_logs(ids: Identifiers) -> Iterator[None]:
    """While active, every handler of the root logger scrubs ``ids`` from its records."""
    if not ids:
        yield
        return
    flt = ScrubFilter(ids)
    handlers = list(logging.getLogger().handlers)
    for h in handlers:
        h.addFilter(flt)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(flt)


# ----------------------------------------------------------------------------- DICOM out
def deidentify_dataset(ds: Any, *, pseudonym: str) -> Any:
    """Apply the Basic Application Level Confidentiality Profile (DICOM PS3.15 E.1) to
    ``ds`` in place, for the attributes regtrack writes; return ``ds``.

    Actions (:data:`BASIC_PROFILE_ACTIONS`): PatientName and PatientID get the pseudonym
    (dummy value "D"), Type-2 dates/times/numbers are emptied ("Z"), the other
    identifying attributes of :data:`IDENTIFYING_KEYWORDS` and all private tags are
    removed ("X").  PatientIdentityRemoved = YES, DeidentificationMethod and
    DeidentificationMethodCodeSequence (113100, DCM) record it.
    """
    from pydicom.dataset import Dataset

    if not pseudonym or any(c in pseudonym for c in "^\\"):
        raise ValueError(f"pseudonym {pseudonym!r}: give a non-empty id without '^' or '\\'")
    for kw, action in BASIC_PROFILE_ACTIONS.items():
        if action == "D":
            setattr(ds, kw, pseudonym)
        elif kw in ds:
            if action == "Z":
                setattr(ds, kw, "")
            else:
                delattr(ds, kw)
    for kw in IDENTIFYING_KEYWORDS:
        if kw not in BASIC_PROFILE_ACTIONS and kw in ds:
            delattr(ds, kw)
    ds.remove_private_tags()
    ds.PatientIdentityRemoved = "YES"
    ds.DeidentificationMethod = DEIDENTIFICATION_METHOD
    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = BASIC_PROFILE_CODE
    ds.DeidentificationMethodCodeSequence = [item]
    return ds


def dicom_leaks(path: str | os.PathLike, *, pseudonym: str | None = None) -> list[str]:
    """Identifying attributes of a DICOM file that break the basic profile (empty = clean).

    Allowed: PatientName/PatientID equal to ``pseudonym`` (when given), empty Type-2
    attributes, and PatientIdentityRemoved = YES must be present.
    """
    import pydicom

    ds = pydicom.dcmread(path, stop_before_pixels=True)
    bad = []
    for kw in IDENTIFYING_KEYWORDS:
        value = str(ds.get(kw, "") or "").strip()
        if not value:
            continue
        if kw in ("PatientName", "PatientID") and pseudonym is not None and value == pseudonym:
            continue
        bad.append(f"{kw}={value!r}")
    if str(ds.get("PatientIdentityRemoved", "")).upper() != "YES":
        bad.append("PatientIdentityRemoved is not YES")
    if any(elem.tag.is_private for elem in ds):
        bad.append("private tags present")
    return bad


def files_under(folder: str | os.PathLike) -> Iterable[Path]:
    """Every regular file below ``folder`` (sorted)."""
    return sorted(p for p in Path(folder).rglob("*") if p.is_file())


__all__ = [
    "BASIC_PROFILE_ACTIONS", "IDENTIFYING_KEYWORDS", "Identifiers", "ScrubFilter",
    "collect_identifiers", "deidentify_dataset", "dicom_leaks", "files_under",
    "identifiers_of_case_folder",
    "pseudonymous_id", "read_identifiers", "scrub_logs",
]
