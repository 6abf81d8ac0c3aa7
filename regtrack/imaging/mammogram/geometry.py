"""Acquisition geometry in a mammogram's DICOM header, checked before it is used.

Read (DICOM PS3.3, X-Ray Acquisition Dose / DX Positioning / Mammography modules):

============================================  ==========  ====================================
tag                                           plausible   used for
============================================  ==========  ====================================
BodyPartThickness (0018,11A0)                 10-150 mm   the final plate gap of the view
CompressionForce (0018,11A2)                  20-300 N    reported beside the simulated force
PositionerPrimaryAngle (0018,1510)            30-70 deg   the MLO plate angle (its magnitude)
DistanceSourceToDetector (0018,1110)          500-1000 mm cone-beam projection (SID)
DistanceSourceToPatient (0018,1111)           300-1000 mm source to the breast support (SSD)
EstimatedRadiographicMagnificationFactor      1.0-2.5     SSD = SID / factor when SSD is absent
(0018,1114)
============================================  ==========  ====================================

A value that is missing, not a single finite number (wrong VR, several values) or outside
its range is dropped with a one-line warning naming the tag, and the caller falls back to
case.toml or the default: nothing here raises.

CompressionForce is defined in newtons, but some units store decanewtons (daN); a
diagnostic compression is about 50-200 N, so a value in [2, 30] is read as daN (x 10)
and one in [30, 300] as N; the unit and why are recorded.  It is never used as a load,
only reported.

PositionerPrimaryAngle: the sign gives the direction of the C-arm rotation, which differs
between the left and the right breast (and between vendors); the plate frame of regtrack
already mirrors the MLO for the side (:func:`regtrack.virtual.frames.plate_frame`), so
the magnitude is the plate angle.  Only MLO views use it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

#: keyword -> (tag, low, high, unit) of the plausible range
RANGES = {
    "BodyPartThickness": ("(0018,11A0)", 10.0, 150.0, "mm"),
    "CompressionForce": ("(0018,11A2)", 2.0, 300.0, "N"),
    "PositionerPrimaryAngle": ("(0018,1510)", 30.0, 70.0, "deg"),
    "DistanceSourceToDetector": ("(0018,1110)", 500.0, 1000.0, "mm"),
    "DistanceSourceToPatient": ("(0018,1111)", 300.0, 1000.0, "mm"),
    "EstimatedRadiographicMagnificationFactor": ("(0018,1114)", 1.0, 2.5, ""),
}

#: CompressionForce values in [DAN_LOW, DAN_HIGH] are decanewtons
DAN_LOW, DAN_HIGH = 2.0, 30.0


@dataclass
class DicomGeometry:
    """The plausible geometry values of one mammogram's header (None: absent or dropped).

    ``force_N`` is converted to newtons (``force_unit`` says what was stored and why);
    ``angle_deg`` is the magnitude of PositionerPrimaryAngle; ``spacing_magnification`` the
    magnification at which the image's pixel spacing is calibrated (1: the detector;
    ``ImagerPixelSpacing / PixelSpacing`` or the magnification factor the reader divides
    by: a plane above the detector, usually the breast support).  ``warnings`` holds one
    line per value dropped.
    """

    thickness_mm: float | None = None
    force_N: float | None = None
    force_raw: float | None = None
    force_unit: str | None = None
    angle_deg: float | None = None
    angle_raw: float | None = None
    sid_mm: float | None = None
    ssd_mm: float | None = None
    ssd_from: str | None = None
    magnification: float | None = None
    spacing_magnification: float = 1.0
    manufacturer: str = ""
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in (
            "thickness_mm", "force_N", "force_raw", "force_unit", "angle_deg", "angle_raw",
            "sid_mm", "ssd_mm", "ssd_from", "magnification", "spacing_magnification",
            "manufacturer", "warnings")}


def _number(ds, keyword: str, name: str, warnings: list[str]) -> float | None:
    """The tag's single finite value, or None (absent: silently; malformed: a warning)."""
    tag = RANGES[keyword][0]
    try:
        raw = ds.get(keyword)
    except Exception as exc:  # noqa: BLE001 - a malformed element must not stop the run
        warnings.append(f"{name}: {keyword} {tag} unreadable ({type(exc).__name__}); ignored")
        return None
    if raw is None or raw == "":
        return None
    try:
        if isinstance(raw, (list, tuple)) or type(raw).__name__ == "MultiValue":
            raise TypeError("several values")
        value = float(raw)
    except (TypeError, ValueError) as exc:
        warnings.append(f"{name}: {keyword} {tag} = {str(raw)[:40]!r} is not a single number "
                        f"({exc}); ignored, fix the tag or set the value in case.toml")
        return None
    if not math.isfinite(value):
        warnings.append(f"{name}: {keyword} {tag} = {value} is not finite; ignored")
        return None
    return value


def _in_range(keyword: str, value: float | None, name: str, warnings: list[str],
              *, what: str = "") -> float | None:
    if value is None:
        return None
    tag, lo, hi, unit = RANGES[keyword]
    if lo <= value <= hi:
        return value
    warnings.append(f"{name}: {keyword} {tag} = {value:g} {unit}".rstrip() + f" is implausible "
                    f"(expected {lo:g}-{hi:g} {unit}{what}); ignored, "
                    "the case.toml value or the default is used")
    return None


def _spacing_magnification(ds, sid: float | None, ssd: float | None) -> float:
    """Magnification of the plane at which the pixel spacing the reader uses is given
    (``regtrack.imaging.mammogram.dicom._spacing_from_tags``)."""
    def pair(keyword):
        try:
            v = ds.get(keyword)
            vals = [float(x) for x in v] if v is not None else []
        except (TypeError, ValueError):
            return None
        return vals[0] if len(vals) == 2 and all(math.isfinite(x) and x > 0 for x in vals) else None

    ps, ips = pair("PixelSpacing"), pair("ImagerPixelSpacing")
    mag = None
    if ps is not None and ips is not None:
        mag = ips / ps
    elif ps is None and ips is not None:
        try:
            m = float(ds.get("EstimatedRadiographicMagnificationFactor"))
            mag = m if math.isfinite(m) and m > 0 else None
        except (TypeError, ValueError):
            mag = None
    if mag is None or mag < 1.0 + 1e-3:
        return 1.0
    if sid and ssd:  # never a plane above the breast support
        mag = min(mag, sid / ssd)
    return float(mag)


def read_geometry(ds, *, name: str = "mammogram", view: str | None = None) -> DicomGeometry:
    """The plausible geometry values of a pydicom dataset (header only); never raises.

    Parameters
    ----------
    ds : pydicom.Dataset
    name : str
        How warnings name the file (e.g. ``"[views.CC] cc.dcm"``).
    view : {"CC", "MLO"}, optional
        PositionerPrimaryAngle is read for MLO only.
    """
    w: list[str] = []
    g = DicomGeometry(manufacturer=str(ds.get("Manufacturer", "") or "")[:64])
    g.thickness_mm = _in_range("BodyPartThickness",
                               _number(ds, "BodyPartThickness", name, w), name, w)
    f = _number(ds, "CompressionForce", name, w)
    if f is not None:
        g.force_raw = f
        f = _in_range("CompressionForce", f, name, w, what=", or 2-30 daN")
        if f is not None:
            if f <= DAN_HIGH:
                g.force_N, g.force_unit = 10.0 * f, (
                    f"daN (a value of {f:g} is {10 * f:g} N; {f:g} N is below any diagnostic "
                    f"compression{', vendor ' + g.manufacturer if g.manufacturer else ''})")
            else:
                g.force_N, g.force_unit = f, "N"
    if view is None or str(view).upper() == "MLO":
        a = _number(ds, "PositionerPrimaryAngle", name, w)
        if a is not None:
            g.angle_raw = a
            g.angle_deg = _in_range("PositionerPrimaryAngle", abs(a), name, w,
                                    what=" in magnitude for an MLO")
    sid = _in_range("DistanceSourceToDetector",
                    _number(ds, "DistanceSourceToDetector", name, w), name, w)
    ssd = _in_range("DistanceSourceToPatient",
                    _number(ds, "DistanceSourceToPatient", name, w), name, w)
    mag = _in_range("EstimatedRadiographicMagnificationFactor",
                    _number(ds, "EstimatedRadiographicMagnificationFactor", name, w), name, w)
    g.magnification = mag
    if sid is not None and ssd is not None and ssd >= sid:
        w.append(f"{name}: DistanceSourceToPatient (0018,1111) = {ssd:g} mm is not shorter than "
                 f"DistanceSourceToDetector (0018,1110) = {sid:g} mm; both ignored (orthogonal "
                 "projection)")
        sid = ssd = None
    if sid is not None:
        if ssd is not None:
            g.ssd_from = "DistanceSourceToPatient (0018,1111)"
        elif mag is not None:
            ssd = sid / mag
            g.ssd_from = "DistanceSourceToDetector / EstimatedRadiographicMagnificationFactor"
    g.sid_mm, g.ssd_mm = sid, ssd
    g.spacing_magnification = _spacing_magnification(ds, sid, ssd)
    g.warnings = w
    return g


def read_geometry_file(path, *, name: str | None = None, view: str | None = None) -> DicomGeometry:
    """:func:`read_geometry` of a DICOM file's header; an unreadable file gives an empty
    geometry with a warning (the reader of the pixels reports the real problem)."""
    import pydicom

    label = name or str(path)
    try:
        ds = pydicom.dcmread(str(path), stop_before_pixels=True, force=True)
    except Exception as exc:  # noqa: BLE001
        msg = f"{label}: header unreadable ({type(exc).__name__}); no DICOM geometry used"
        return DicomGeometry(warnings=[msg])
    return read_geometry(ds, name=label, view=view)
