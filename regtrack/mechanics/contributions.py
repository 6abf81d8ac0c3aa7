"""The plug-in interface between the nonlinear solver and extra force terms (contact).

The solver (``regtrack.mechanics.solver``) finds the displacement ``u`` (N, 3) of the
model nodes such that the residual

    R(u) = f_int(u) + sum_c r_c(u) - f_ext(t) = 0

where ``f_int`` is the tissue + skin internal force, ``f_ext`` gravity, and each
*contribution* ``c`` (e.g. a rigid plate with frictional contact) adds a residual
``r_c`` and its consistent tangent ``K_c = d r_c / d u``.  All vectors are flattened
node-major: dof ``3*i + k`` is component ``k`` of node ``i``.  Units: mm, N, MPa.

A load step runs a pseudo-time ``t`` from 0 to 1; the solver calls, in this order:

* ``begin_step(step)`` once when a protocol step starts (plates read their motion);
* ``set_time(t)`` before each increment (a plate moves to its position at ``t``);
* ``residual_tangent(u)`` at every Newton iterate;
* ``commit(u)`` after an increment converged (friction stores its stick point /
  slip history); ``rollback()`` if the increment is cut back;
* ``augment(u) -> bool`` after convergence when the contribution uses augmented
  Lagrangian multipliers: return True when the multipliers are converged, False to
  ask the solver to re-solve the increment with the updated multipliers;
* ``report(u) -> dict`` after each converged increment: plain figures (force on the
  plate in N, maximum penetration in mm, number of active nodes, contact area mm^2).

Optional: ``carry_multipliers(u)``, called just before ``commit`` of an increment that
ends before t = 1 (solver ``augmentation = "final"``, where such increments skip the
``augment`` re-solves): update the multipliers once, for ``commit`` to carry into the
next increment.

Optional: ``trial_state() -> state`` and ``set_trial_state(state, *, solve_state=True)``:
a copy of the current solve's multipliers (and discrete state), and its restoration.
After a stabilised increment the solver starts the undamped "settle" solve at the same
load from those multipliers (``solve_state=False``) and, if the settle fails, restores the
whole state, so that ``commit`` stores the stabilised solve's.

Optional: ``freeze()``, called when Newton stagnates, asks the contribution to hold its
discrete state (stick/slip) for the rest of the solve and to check it in ``augment``;
a contribution without it is left alone.

Optional: ``preconditioner_tangent()``, called after ``residual_tangent``, returns a
matrix of the same pattern as that tangent whose (symmetric part's) factorisation
preconditions the linear solves better than the symmetric part of the tangent itself, or
None (plate contact: the tangent without the sliding nodes' friction-bound term, which is
symmetric; solver option ``preconditioner``).  It changes only the linear solves, never
the residual or the converged state.

Optional: ``swap_tangent() -> bool`` switches the contribution to its alternative tangent
(plate contact: with or without the rounded-edge curvature term) and returns True, or
returns False when it has none; the solver calls it to retry a failed increment with the
other tangent before cutting back, and calls it again afterwards to switch back.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp


@runtime_checkable
class Contribution(Protocol):
    name: str

    def begin_step(self, step: Any) -> None: ...

    def set_time(self, t: float) -> None: ...

    def residual_tangent(self, u: np.ndarray) -> tuple[np.ndarray, sp.spmatrix | None]:
        """Residual (3N,) and tangent (3N, 3N) sparse (None if no active node)."""
        ...

    def commit(self, u: np.ndarray) -> None: ...

    def rollback(self) -> None: ...

    def augment(self, u: np.ndarray) -> bool: ...

    def report(self, u: np.ndarray) -> dict: ...
