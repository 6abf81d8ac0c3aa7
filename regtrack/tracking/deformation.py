"""The finite-element deformation as a map between the MRI and a compressed state, both ways.

The patient model is a linear (P1) tetrahedral mesh with reference node positions ``X``
(the prone MRI) and, after a protocol, deformed positions ``x = X + u``.  The deformation
of the mesh is piecewise linear: a point ``P`` of reference tetrahedron ``e`` with
barycentric coordinates ``lambda`` (:mod:`regtrack.tracking.locate`) goes to

.. math::

    \\varphi(P) = \\sum_{k=0}^{3} \\lambda_k x_{e,k}, \\qquad
    \\lambda = \\mathrm{bary}_e(P; X),

and a point ``p`` of the compressed breast comes back through the deformed tetrahedron that
contains it, ``\\varphi^{-1}(p) = \\sum_k \\mu_k X_{e,k}`` with ``\\mu = \\mathrm{bary}_e(p; x)``.
Both are exact inverses of each other on the mesh (up to round-off) as long as no element
is inverted, which the guard rails of the simulation check.

Points are given and returned in the patient frame (LPS, mm, the MRI's own frame): the
compressed state is expressed in the same frame of reference as the MRI, so it can be
overlaid on a compressed MRI of the same session (Chung et al. 2008).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from regtrack.errors import TrackingError
from regtrack.model.types import AnatomicalFrame
from regtrack.tracking.locate import TetLocator


@dataclass
class DeformationMap:
    """Forward and inverse map of one simulated compression (patient frame, mm).

    Parameters
    ----------
    reference : (N, 3) float
        Reference node positions, model frame (mm).
    deformed : (N, 3) float
        Deformed node positions, model frame (mm).
    tets : (E, 4) int
    frame : AnatomicalFrame
        Model frame <-> patient (LPS) frame.
    view : str
        Name of the compressed state, for messages ("CC", "MLO", "BIOPSY").
    """

    reference: np.ndarray
    deformed: np.ndarray
    tets: np.ndarray
    frame: AnatomicalFrame
    view: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_model(cls, model, deformed: np.ndarray, *, view: str = "") -> DeformationMap:
        """The map of a :class:`~regtrack.model.types.BreastModel` and its deformed nodes."""
        return cls(model.points, np.asarray(deformed, float), model.tets, model.frame, view)

    @cached_property
    def reference_locator(self) -> TetLocator:
        return TetLocator(self.reference, self.tets)

    @cached_property
    def deformed_locator(self) -> TetLocator:
        return TetLocator(self.deformed, self.tets)

    def forward_model(self, points_model) -> np.ndarray:
        """(M, 3) reference points, model frame -> deformed (NaN outside the mesh)."""
        loc = self.reference_locator.locate(np.atleast_2d(points_model))
        return loc.interpolate(self.tets, self.deformed)

    def inverse_model(self, points_model) -> np.ndarray:
        """(M, 3) deformed points, model frame -> reference (NaN outside the mesh)."""
        loc = self.deformed_locator.locate(np.atleast_2d(points_model))
        return loc.interpolate(self.tets, self.reference)

    def forward(self, lps_mm, *, names=None) -> np.ndarray:
        """MRI points (M, 3) LPS mm -> their positions in the compressed state (LPS mm).

        Raises :class:`TrackingError` naming the first point outside the breast model."""
        q = np.atleast_2d(np.asarray(lps_mm, float))
        out = self.forward_model(self.frame.to_model(q))
        self._check(q, out, names, "MRI", self.reference_locator)
        return self.frame.to_patient(out)

    def inverse(self, lps_mm, *, names=None) -> np.ndarray:
        """Points of the compressed state (M, 3) LPS mm -> the MRI (LPS mm).

        Raises :class:`TrackingError` naming the first point outside the compressed breast."""
        q = np.atleast_2d(np.asarray(lps_mm, float))
        out = self.inverse_model(self.frame.to_model(q))
        self._check(q, out, names, f"compressed {self.view}".rstrip(), self.deformed_locator)
        return self.frame.to_patient(out)

    def _check(self, q, out, names, where: str, locator: TetLocator) -> None:
        bad = np.flatnonzero(~np.isfinite(out).all(axis=1))
        if not len(bad):
            return
        i = int(bad[0])
        d = float(locator.distance_to_nodes(self.frame.to_model(q[i]))[0])
        who = f"{names[i]} " if names is not None else ""
        more = f" ({len(bad)} of {len(q)} points)" if len(bad) > 1 else ""
        raise TrackingError(f"point {who}({', '.join(f'{v:.1f}' for v in q[i])}) LPS mm is "
                            f"outside the {where} breast model{more}, {d:.1f} mm from its "
                            "nearest node; give a point inside the breast")
