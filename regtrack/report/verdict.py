"""The report's verdict: fit-quality checks of each view against stated thresholds.

A check that fails does not stop the pipeline: it is printed on the report's first page,
so that a poor fit is never read as a good one.  The thresholds:

* **BS_Av >= 30 %** (:data:`BS_AV_MIN`).  BS_Av is the share of the summed breast-contour
  distance left by the nipple superposition that the rotation theta_p removes (eq. 4 of
  Lapuebla-Ferri et al.).  The demo phantom, mammograms rotated by +5 and -4 degrees and a
  deliberately mismatched tissue model, gives 57 and 73 %; a model that does not resemble
  the breast leaves most of the mismatch (a mismatched case gave 4.8 %).
* **|theta_p| <= 10 degrees** (:data:`THETA_MAX_DEG`).  The in-plane rotation between a
  compressed model and a mammogram is a positioning difference of a few degrees; more
  points to a wrong nipple, a wrong orientation of the image, or a poor model.
* **d_B <= 10 mm** (:data:`D_B_MAX_MM`): the distance between the real and virtual breast
  centroids after alignment (the demo: 5.7 and 4.5 mm).
* **Force balance <= [mechanics.solver] stall_force_tol** (0.005 by default): the resultant
  of the residual over the free nodes relative to the largest load of any step
  (:func:`regtrack.mechanics.problem.force_balance`); converged states give about 1e-7.
* **Skin inside the tissue <= 1 mm** (``[contact] skin_overlap_warn_mm``'s default): the
  deepest a skin node ended a step inside the tissue (:mod:`regtrack.mechanics.overlap`).
  The self-contact barrier keeps skin out of other skin, but not where the crease is
  sharper than the mesh (:mod:`regtrack.mechanics.selfcontact`); the shape there is then
  not physical.  The phantom has none (docs/physics.md: the cohort with and without the
  barrier).
* **Nipple confidence >= 0.5** (:data:`NIPPLE_CONFIDENCE_MIN`): ``1 / (1 + (u / 10 mm)^2)``
  with ``u`` the tangential uncertainty of the detected nipple
  (:mod:`regtrack.imaging.mammogram.nipple`), so 0.5 means +-10 mm along the contour; a
  nipple given in case.toml (``nipple_px``) has confidence 1.  The registration then
  places a detected nipple along the skin line where the outlines agree
  (:mod:`regtrack.registration.align`), so a low confidence asks for a look at the
  overlay rather than meaning a wrong superposition.
"""

from __future__ import annotations

from dataclasses import dataclass

from regtrack.report.fmt import num, sci

BS_AV_MIN = 30.0
THETA_MAX_DEG = 10.0
D_B_MAX_MM = 10.0
NIPPLE_CONFIDENCE_MIN = 0.5
#: [mechanics.solver] stall_force_tol default, used when a result does not carry its own
FORCE_BALANCE_TOL = 0.005
#: [contact] skin_overlap_warn_mm default (mm)
SKIN_OVERLAP_MAX_MM = 1.0


@dataclass(frozen=True)
class Check:
    """One quality check of one view; ``ok`` is None when the figure is not available."""

    name: str
    short: str
    view: str
    value: str
    threshold: str
    ok: bool | None
    advice: str = ""


def _ok(value, test) -> bool | None:
    return None if value is None else bool(test(float(value)))


def force_balance(simulation: dict | None) -> tuple[float | None, float]:
    """(largest relative force imbalance over the steps, its tolerance) of a simulation
    (``{"summary": ..., "steps": ...}`` as in the result JSON)."""
    simulation = simulation or {}
    summary = simulation.get("summary") or simulation
    rel = summary.get("force_imbalance_rel")
    tols = [s["solver"]["force_balance"]["tol"] for s in simulation.get("steps") or []
            if isinstance((s.get("solver") or {}).get("force_balance"), dict)]
    return rel, (max(tols) if tols else FORCE_BALANCE_TOL)


def check_view(view: str, row: dict, *, simulation: dict | None = None,
               nipple: dict | None = None) -> list[Check]:
    """The checks of one view.

    Parameters
    ----------
    row : dict
        The view's metrics row (``BS_Av`` %, ``theta_p`` degrees, ``d_B`` mm).
    simulation : dict, optional
        The simulation result (``summary`` with ``force_imbalance_rel`` and
        ``skin_overlap_mm``, ``steps``).
    nipple : dict, optional
        The real view's nipple record (``meta["nipple"]``: ``confidence``, ``method``).
    """
    bs, th, db = row.get("BS_Av"), row.get("theta_p"), row.get("d_B")
    rel, tol = force_balance(simulation)
    skin = ((simulation or {}).get("summary") or {}).get("skin_overlap_mm")
    conf = (nipple or {}).get("confidence")
    how = (nipple or {}).get("method", "")
    out = [
        Check("Breast similarity BS_Av", "BS_Av", view, num(bs, 1, unit="%"), f"≥ {BS_AV_MIN:g} %",
              _ok(bs, lambda x: x >= BS_AV_MIN),
              "the rotation removes little of the contour mismatch: compare the overlays"),
        Check("Rotation θp", "θp", view, num(th, 1, unit="°", signed=True),
              f"within ±{THETA_MAX_DEG:g}°", _ok(th, lambda x: abs(x) <= THETA_MAX_DEG),
              "check the nipple, the image orientation and the model"),
        Check("Breast centroid distance d_B", "d_B", view, num(db, 1, unit="mm"), f"≤ {D_B_MAX_MM:g} mm",
              _ok(db, lambda x: x <= D_B_MAX_MM), "the virtual breast is displaced or misshapen"),
        Check("Force balance (relative)", "force balance", view, sci(rel), f"≤ {tol:g}",
              _ok(rel, lambda x: x <= tol), "the simulation is not in equilibrium"),
        Check("Skin inside the tissue", "skin in tissue", view, num(skin, 1, unit="mm"),
              f"≤ {SKIN_OVERLAP_MAX_MM:g} mm", _ok(skin, lambda x: x <= SKIN_OVERLAP_MAX_MM),
              "the skin folded through itself (a crease sharper than the mesh, or "
              "[contact] self_contact_gap_mm = 0): the shape near the fold is not physical"),
        Check("Nipple confidence", "nipple confidence", view,
              num(conf, 2) + (" (given)" if "given" in how else ""),
              f"≥ {NIPPLE_CONFIDENCE_MIN:g}", _ok(conf, lambda x: x >= NIPPLE_CONFIDENCE_MIN),
              "the registration placed it where the outlines agree: check the overlay, "
              "or give nipple_px in case.toml"),
    ]
    return out


def verdict_line(checks: list[Check]) -> str:
    """One sentence: every check passed, or which failed."""
    failed = [c for c in checks if c.ok is False]
    done = [c for c in checks if c.ok is not None]
    if not done:
        return "No quality check could be made (no registration)."
    if not failed:
        return f"All {len(done)} quality checks passed."
    what = "; ".join(f"{c.view} {c.short} {c.value} (limit {c.threshold})" for c in failed)
    return f"{len(failed)} of {len(done)} quality checks flagged: {what}."
