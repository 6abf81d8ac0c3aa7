"""Error of a surrogate against full simulations: held-out points and leave-one-out.

The error at a node is the Euclidean distance (mm) between the predicted and the simulated
displacement, :math:`e_i = \\lVert \\hat u_i - u_i \\rVert`; a point's error is summarised by
the median, the 95th percentile and the maximum over the nodes (the issue's acceptance:
median <= 1 mm, 95th percentile <= 2 mm).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def nodal_errors(predicted: np.ndarray, simulated: np.ndarray) -> np.ndarray:
    """Distance (mm) per node between two ``(..., N, 3)`` displacement fields."""
    return np.linalg.norm(np.asarray(predicted, float) - np.asarray(simulated, float), axis=-1)


def error_summary(errors: np.ndarray) -> dict[str, float]:
    """``median_mm``, ``p95_mm`` and ``max_mm`` of nodal errors (mm)."""
    e = np.ravel(errors)
    return {"median_mm": float(np.median(e)), "p95_mm": float(np.percentile(e, 95)),
            "max_mm": float(e.max())}


def held_out(surrogate, params: np.ndarray, fields: np.ndarray) -> dict:
    """Per held-out point and pooled error of ``surrogate`` against ``fields`` (``(m, N, 3)``)."""
    p = np.atleast_2d(np.asarray(params, float))
    pred = surrogate.predict(p)
    errs = nodal_errors(pred, fields)
    points = [{"params": dict(zip(surrogate.names, map(float, p[i]))), **error_summary(errs[i])}
              for i in range(len(p))]
    return {"points": points, "pooled": error_summary(errs)}


def leave_one_out(fit: Callable[[np.ndarray, np.ndarray], object], params: np.ndarray,
                  fields: np.ndarray) -> dict:
    """Leave-one-out error: ``fit(params, fields)`` on all points but one, predict that one.

    ``fit`` returns an object with ``predict((1, d)) -> (1, N, 3)``.  Returns the per-point
    summaries (:func:`error_summary`) and the pooled one over every node of every point."""
    p = np.atleast_2d(np.asarray(params, float))
    u = np.asarray(fields, float)
    errs = []
    for i in range(len(p)):
        keep = np.arange(len(p)) != i
        model = fit(p[keep], u[keep])
        errs.append(nodal_errors(model.predict(p[i:i + 1])[0], u[i]))  # type: ignore[attr-defined]
    e = np.asarray(errs)
    return {"points": [error_summary(x) for x in e], "pooled": error_summary(e)}
