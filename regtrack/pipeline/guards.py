"""Numerical guard rails: results are checked before a later stage uses them.

A failed check raises :class:`~regtrack.errors.ResultCheckError` whose message names the
stage (``simulate CC: ...``) and the figure that failed, never a silent report.

Checks on a simulation (:func:`check_simulation`):

* the protocol completed and recorded no error (the solver's converged flag);
* every deformed node position is finite;
* no element is inverted: the deformed signed volume of every tetrahedron is positive,
  :math:`J_e = V_e(\\mathbf{x}) / V_e(\\mathbf{X}) > J_{min}` with
  :data:`MIN_VOLUME_RATIO`;
* the deepest plate penetration of every step is within ``[contact]
  max_penetration_mm``;
* the compression degree :math:`D` is finite and in [0, 1).

Checks on the 2-D stages (:func:`check_metrics_row`): every metric reported is finite or
explicitly absent (None).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from regtrack.errors import ResultCheckError

#: smallest accepted deformed/reference volume ratio of a tetrahedron (an element squeezed
#: to a millionth of its volume is numerically inverted for every purpose here)
MIN_VOLUME_RATIO = 1e-6


def check_simulation(stage: str, doc: dict, positions: np.ndarray, model: Any, *,
                     max_penetration_mm: float) -> None:
    """Raise :class:`ResultCheckError` naming ``stage`` when a simulation is unusable.

    Parameters
    ----------
    stage : str
        E.g. ``"simulate CC"``.
    doc : dict
        The result JSON (``summary``, ``steps``, ``error``).
    positions : (N, 3) float
        Deformed node positions (mm).
    model : BreastModel
        Reference mesh (``tets``, ``tet_volumes``).
    max_penetration_mm : float
        Accepted penetration bound (mm), ``[contact] max_penetration_mm``.
    """
    summary = doc.get("summary") or {}
    if doc.get("error"):
        raise ResultCheckError(f"{stage}: the solver reported an error ({doc['error']}); the "
                               "result is not used")
    if summary.get("complete") is False:
        raise ResultCheckError(f"{stage}: the protocol did not complete (converged flag false); "
                               "relax [contact]/[mechanics] settings or the protocol targets")
    x = np.asarray(positions, float)
    if x.shape != (model.n_nodes, 3):
        raise ResultCheckError(f"{stage}: {x.shape} deformed positions for a model of "
                               f"{model.n_nodes} nodes; the cached result belongs to another mesh")
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        raise ResultCheckError(f"{stage}: {int(bad.sum())} node position(s) are not finite "
                               "(NaN/inf); the solution diverged")
    v0 = model.tet_volumes()
    ratio = model.tet_volumes(x) / np.where(v0 > 0, v0, np.nan)
    inverted = ~(ratio > MIN_VOLUME_RATIO)
    if inverted.any():
        raise ResultCheckError(f"{stage}: {int(inverted.sum())} of {len(ratio)} element(s) "
                               f"inverted or collapsed (smallest volume ratio "
                               f"{np.nanmin(ratio):.3g}); refine the mesh ([model] "
                               "target_nodes) or cut the load step")
    pen = [float(s.get("max_penetration_mm") or 0.0) for s in doc.get("steps") or []]
    pen.append(float(summary.get("max_penetration_mm") or 0.0))
    worst = max(pen)
    if not math.isfinite(worst) or worst > max_penetration_mm:
        raise ResultCheckError(f"{stage}: plate penetration {worst:.3g} mm exceeds [contact] "
                               f"max_penetration_mm = {max_penetration_mm:g} mm")
    D = summary.get("D")
    if D is not None and not (math.isfinite(float(D)) and 0.0 <= float(D) < 1.0):
        raise ResultCheckError(f"{stage}: compression degree D = {D} is outside [0, 1)")


#: metrics every row must carry as a finite number (others may be None)
REQUIRED_METRICS = ("BS_Av", "theta_p_b", "theta_p", "d_B")


def check_metrics_row(stage: str, row: dict) -> None:
    """Every number of a metrics row is finite; the required ones are present."""
    for key, value in row.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise ResultCheckError(f"{stage}: {key} = {value} is not finite; the registration "
                                   "inputs are degenerate")
    missing = [k for k in REQUIRED_METRICS if row.get(k) is None]
    if missing:
        raise ResultCheckError(f"{stage}: {', '.join(missing)} could not be computed")
