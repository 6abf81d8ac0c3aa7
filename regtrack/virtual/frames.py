"""Plate frames: the compression geometry shared by mechanics and the virtual mammogram.

One source of truth for the orientation of the mammographic plates in the model frame
(:mod:`regtrack.model.types`: origin = nipple, ``x`` anterior, ``y`` superior, ``z``
patient right).  The medial unit vector is ``m = -z`` for a right breast and ``m = +z``
for a left one.

For a view angle :math:`\\theta` (0 deg for CC, 45 deg by default for MLO)

.. math::

    n = \\cos\\theta\\,y + \\sin\\theta\\,m, \\qquad
    e_x = x, \\qquad
    e_{down} = \\cos\\theta\\,m - \\sin\\theta\\,y

``n`` points from the lower (receptor) plate towards the upper (compression) plate,
``e_x`` and ``e_down`` span the plate plane.  The 2-D coordinates of a 3-D point ``p``
projected on the plate are

.. math::

    (X, Y) = ((p - o)\\cdot e_x,\\; (p - o)\\cdot e_{down})

which is exactly the canonical 2-D frame of :mod:`regtrack.views` (``X`` posterior to
anterior, nipple to the right; ``Y`` down = medial for CC, infero-medial for MLO).
Real and virtual views therefore share one frame, and the registration's nominal angle
is 0 deg for both views: the 45 deg pre-rotation of the MLO virtual mammogram in
Lapuebla-Ferri et al. is built into the MLO plate frame.

Note that ``(e_x, e_down, n)`` is right-handed for a right breast and left-handed for a
left breast: the canonical display is the standard view of a *left* breast, so a right
breast is seen mirrored, as radiologists display it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regtrack.errors import ConfigError

#: Nominal plate angle (degrees) per view.  "BIOPSY" is the latero-medial compression of
#: the prone breast in an MR biopsy coil (plates in the sagittal plane, ``n`` medial); it
#: has no mammogram.
NOMINAL_ANGLE_DEG = {"CC": 0.0, "MLO": 45.0, "BIOPSY": 90.0}


@dataclass(frozen=True)
class PlateFrame:
    """Orientation of the mammographic plates in the model frame (mm).

    Attributes
    ----------
    origin : (3,) float
        A point of the lower (receptor) plate plane, mm, model frame.
    normal : (3,) float
        Unit normal ``n`` from the lower (receptor) plate towards the upper
        (compression) plate.
    e_x : (3,) float
        In-plane unit vector, posterior -> anterior (2-D ``X``, nipple to the right).
    e_down : (3,) float
        In-plane unit vector, 2-D ``Y`` (image "down"): medial (CC) / infero-medial (MLO).
    view : str
        "CC" or "MLO".
    side : str
        "L" or "R".
    angle_deg : float
        Rotation angle theta (degrees) of the plate about the antero-posterior axis.
    """

    origin: np.ndarray
    normal: np.ndarray
    e_x: np.ndarray
    e_down: np.ndarray
    view: str
    side: str
    angle_deg: float

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rows ``e_x, e_down, n``: maps model vectors to (X, Y, height)."""
        return np.stack([self.e_x, self.e_down, self.normal])

    def to_plane(self, points) -> np.ndarray:
        """2-D plate coordinates (mm) ``(X, Y)`` of (..., 3) model points."""
        d = np.asarray(points, float) - self.origin
        return np.stack([d @ self.e_x, d @ self.e_down], axis=-1)

    def height(self, points) -> np.ndarray:
        """Signed distance (mm) of (..., 3) points above the lower plate plane along ``n``."""
        return (np.asarray(points, float) - self.origin) @ self.normal

    def to_local(self, points) -> np.ndarray:
        """(..., 3) model points -> (X, Y, h) plate coordinates (mm)."""
        return (np.asarray(points, float) - self.origin) @ self.rotation.T

    def to_model(self, local) -> np.ndarray:
        """(..., 3) plate coordinates (X, Y, h) (mm) -> model points."""
        return np.asarray(local, float) @ self.rotation + self.origin

    def with_origin(self, origin) -> PlateFrame:
        """The same orientation through another origin (mm, model frame)."""
        return PlateFrame(np.asarray(origin, float).reshape(3), self.normal, self.e_x,
                          self.e_down, self.view, self.side, self.angle_deg)

    def to_dict(self) -> dict:
        return {"origin_mm": self.origin.tolist(), "normal": self.normal.tolist(),
                "e_x": self.e_x.tolist(), "e_down": self.e_down.tolist(), "view": self.view,
                "side": self.side, "angle_deg": self.angle_deg}


def medial_unit(side: str) -> np.ndarray:
    """Medial unit vector of the model frame: ``-z`` for a right breast, ``+z`` for a left."""
    if side not in ("L", "R"):
        raise ConfigError(f"breast side {side!r} invalid: use 'L' or 'R' (case.toml [mri] side)")
    return np.array([0.0, 0.0, -1.0 if side == "R" else 1.0])


def plate_frame(view: str, side: str, *, angle_deg: float | None = None,
                origin=(0.0, 0.0, 0.0)) -> PlateFrame:
    """Plate frame of a mammographic view in the model frame.

    Parameters
    ----------
    view : {"CC", "MLO", "BIOPSY"}
        Mammographic view, or the MR biopsy compression (case-insensitive).
    side : {"L", "R"}
        Breast side.
    angle_deg : float, optional
        Plate rotation theta about the antero-posterior axis (degrees); default 0 for CC,
        45 for MLO and 90 for BIOPSY.
    origin : (3,) float
        A point of the lower plate plane (mm, model frame).

    Returns
    -------
    PlateFrame
        With ``n = cos(theta) y + sin(theta) m``, ``e_x = x``,
        ``e_down = cos(theta) m - sin(theta) y``, ``m`` the medial unit vector.
    """
    v = str(view).upper()
    if v not in NOMINAL_ANGLE_DEG:
        raise ConfigError(f"view {view!r} invalid: use one of {', '.join(NOMINAL_ANGLE_DEG)}")
    m = medial_unit(side)
    theta = NOMINAL_ANGLE_DEG[v] if angle_deg is None else float(angle_deg)
    if not np.isfinite(theta):
        raise ConfigError(f"plate angle {angle_deg!r} for view {v} must be a finite number of degrees")
    t = np.deg2rad(theta)
    y = np.array([0.0, 1.0, 0.0])
    n = np.cos(t) * y + np.sin(t) * m
    e_x = np.array([1.0, 0.0, 0.0])
    e_down = np.cos(t) * m - np.sin(t) * y
    return PlateFrame(np.asarray(origin, float).reshape(3), n, e_x, e_down, v, side, theta)
