"""Truth against result, for cases that carry their ground truth (synthetic phantoms).

A case folder may hold ``truth/mammo_truth.json`` and ``truth/phantom_truth.json`` as
written by :mod:`regtrack.phantom` (``pipelines/make_sample_cases.py``).  The pipeline
never uses them to compute anything; the report reads them after the run, to print a
truth-vs-result table.  Frames: in-plane positions in mm of the canonical frame of the
real image (:mod:`regtrack.views`), 3-D positions in LPS mm.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from regtrack.report.fmt import num

log = logging.getLogger(__name__)

MAMMO = "truth/mammo_truth.json"
PHANTOM = "truth/phantom_truth.json"


@dataclass
class Truth:
    """The parts of a case's truth files the report compares."""

    views: dict  # view -> {"rotation_deg", "D", "upper_force_N", "tumour_xy_mm"}
    tumour_volume_mm3: float | None = None
    nipple_lps_mm: list | None = None
    files: tuple[str, ...] = ()

    def tumour_xy(self) -> dict[str, np.ndarray]:
        """True tumour centroid per view (mm, canonical frame of the real image)."""
        return {v: np.asarray(t["tumour_xy_mm"], float) for v, t in self.views.items()
                if t.get("tumour_xy_mm") is not None}


def read_truth(case_root: str | Path | None) -> Truth | None:
    """The case's truth, or None when it has none (or it cannot be read: logged)."""
    if case_root is None:
        return None
    root = Path(case_root)
    mammo, phantom = root / MAMMO, root / PHANTOM
    if not mammo.is_file() and not phantom.is_file():
        return None
    try:
        m = json.loads(mammo.read_text()) if mammo.is_file() else {}
        p = json.loads(phantom.read_text()) if phantom.is_file() else {}
    except (OSError, ValueError) as exc:
        log.warning("%s: truth file not readable (%s); the report has no truth table", root, exc)
        return None
    views = {}
    for v, t in (m.get("views") or {}).items():
        sim = t.get("simulation") or {}
        views[v] = {"rotation_deg": t.get("rotation_deg"), "D": sim.get("D"),
                    "upper_force_N": sim.get("upper_force_N"),
                    "tumour_xy_mm": (t.get("tumour") or {}).get("centroid_canonical_mm")}
    files = tuple(f for f, d in ((MAMMO, m), (PHANTOM, p)) if d)
    return Truth(views, p.get("tumour_volume_mm3"), p.get("nipple_lps_mm"), files)


def truth_table(truth: Truth, results: dict[str, dict], *, tumour_volume_mm3=None,
                nipple_lps_mm=None) -> tuple[list[str], list[list[str]]]:
    """Rows "quantity, view, truth, result, difference" of what both sides have.

    ``results``: per view ``theta_p`` (deg), ``D`` (-), ``force_N`` (N) and
    ``tumour_xy_mm`` (the MRI tumour tracked into the real image, mm).
    """
    head = ["Quantity", "View", "Truth", "Result", "Difference"]
    rows: list[list[str]] = []
    for v, t in truth.views.items():
        r = results.get(v)
        if r is None:
            continue
        pairs = (("In-plane rotation (°)", t["rotation_deg"], r.get("theta_p"), 1.0, 2),
                 ("Compression D (%)", t["D"], r.get("D"), 100.0, 1),
                 ("Upper plate force (N)", t["upper_force_N"], r.get("force_N"), 1.0, 1))
        for name, a, b, scale, dec in pairs:
            if a is not None and b is not None:
                rows.append([name, v, num(scale * a, dec), num(scale * b, dec),
                             num(scale * (b - a), dec, signed=True)])
        xy = r.get("tumour_xy_mm")
        if t.get("tumour_xy_mm") is not None and xy is not None:
            a, b = np.asarray(t["tumour_xy_mm"], float), np.asarray(xy, float)
            rows.append(["Tumour centroid in the image (mm)", v, _xy(a), _xy(b),
                         f"{num(float(np.linalg.norm(b - a)), 1)} mm apart"])
    if truth.tumour_volume_mm3 is not None and tumour_volume_mm3 is not None:
        a, b = truth.tumour_volume_mm3 / 1000.0, tumour_volume_mm3 / 1000.0
        rows.append(["Tumour volume (mL)", "3-D", num(a, 2), num(b, 2),
                     num(100.0 * (b - a) / a, 1, unit="%", signed=True)])
    if truth.nipple_lps_mm is not None and nipple_lps_mm is not None:
        a, b = np.asarray(truth.nipple_lps_mm, float), np.asarray(nipple_lps_mm, float)
        rows.append(["Nipple, LPS (mm)", "3-D", _xy(a), _xy(b),
                     f"{num(float(np.linalg.norm(b - a)), 1)} mm apart"])
    return head, rows


def _xy(p: np.ndarray) -> str:
    return "(" + ", ".join(num(float(c), 1) for c in p) + ")"
