"""Where the supports of a protocol go: the two compression plates placed around the
body and the rigid chest wall behind it.

Plate placement (plate frame ``n, e_x`` of :func:`regtrack.virtual.frames.plate_frame`):
both plates have their chest-wall (posterior) edge rounded with ``edge_radius_mm`` ``r``,
their flat face ending at ``x_cw + e`` (``e = posterior_edge_mm``, ``x_cw = min x`` the
chest-wall plane), and are unbounded elsewhere.  The lower plate faces ``+n``, the upper
one ``-n``; both start ``clearance_mm`` away from every free surface node of the shape the
body has when they are placed (the first plate step of a protocol), measured against
the whole plate surface (rounded edge included: a thick chest-wall base behind the edge
would otherwise start inside the plate, 6.5 mm deep on the phantom's MLO with
``posterior_edge_mm = 10``).

Chest wall: the chest-wall nodes are held normal to the wall and tangentially by a soft
layer while the breast hangs free, and follow the plates along their normal once both hold
it (``[contact] chest_wall_layer_mm``, :mod:`.support`).  Clamped (layer 0, the paper's model), they cannot follow the plates,
whose rounded edges reach to within ``posterior_edge_mm`` of them: the fixed section is
taller than the final plate gap on every exam, and the tissue between a plate's edge and
the clamped nodes is squeezed without limit (docs/performance.md).  ``[contact]
chest_wall_contact`` (on by default) adds a frictionless rigid wall at the chest-wall
plane (:func:`chest_wall`): no node passes behind it into the torso.

**The plates' edge and the wall** (:func:`edge_wedge_problem`).  With the wall, a plate
whose rounded edge reaches in front of the wall, ``0 < e <= r``, meets it at the angle

.. math::

    \\alpha = 90^\\circ - \\arcsin(e / r)

(60 deg at ``e = 5`` mm, ``r = 10`` mm; at ``e = r`` the edge is tangent to the wall, a
crevice of zero angle): an acute wedge that squeezes the tissue of the breast base between
two rigid surfaces.  The nodes pinched there carry more than ten times
the mean pressure under the plate, and their contact multipliers can cycle without
converging at any increment length (docs/performance.md).  The shipped CC and MLO plates
therefore end their flat face at the wall (``e = 0``; a paddle's face reaches the chest
wall): every constraint a node in front of the wall can meet is then a half-space (the face
and the wall, at right angles), so the contact constraints are convex there.  The friction
lag is not, and the right-angled corner still concentrates the pressure on the base.
``e > r`` (the biopsy coil's plates, 20 mm: a 10 mm slot) clears the wall.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from regtrack.errors import ConfigError
from regtrack.mechanics.contact import (ContactConfig, PlateContact, automatic_penalty,
                                        mean_edge_length, tributary_areas)
from regtrack.mechanics.plates import RigidPlate
from regtrack.mechanics.protocol import Protocol

log = logging.getLogger(__name__)


@dataclass
class BodySetup:
    """What the engine needs to know about the body (mm, model frame).

    Attributes
    ----------
    points : (N, 3) float
        Reference node coordinates.
    tets : (E, 4) int
    surface : (S, 3) int
        The outer triangles a plate can touch: the skin, the faces where the MRI's field of
        view or the inframammary fold cut the breast (tissue like any other, without a
        skin membrane), and the chest-wall face when its nodes slide.
    fixed : (N,) bool
        Chest-wall nodes.
    side : {"L", "R"}
    young_mpa : float
        Small-strain Young modulus of the tissue (MPa), for the automatic penalty.
    clamped : bool
        The chest-wall nodes are held in every direction (else they slide on the wall,
        :mod:`.support`, and are plate contact candidates like the rest of the surface).
    target : (3,) float or None
        The lesion's centroid (mm), on which a plate opening is centred; None: the
        breast's surface centroid.
    axes : (3, 3) float or None
        Rows: the model x, y, z axes in the MRI's LPS axes, for gravity given in the
        patient frame (``frame = "patient"``); None: the model frame is LPS-aligned
        (x = anterior, y = superior).
    """

    points: np.ndarray
    tets: np.ndarray
    surface: np.ndarray
    fixed: np.ndarray
    side: str
    young_mpa: float
    clamped: bool = True
    target: np.ndarray | None = None
    axes: np.ndarray | None = None


def chest_wall(body: BodySetup, config: ContactConfig) -> PlateContact | None:
    """Frictionless rigid wall at the chest-wall plane, facing ``+x``: no free node may
    pass behind it (the torso is there).  The plane is ``x = min x`` of the model, the
    most posterior node (the chest-wall nodes of a model cut from an MRI lie within 0.3 mm
    of it), so that no node starts behind it.  Every free node is a contact candidate: a
    surface node with its tributary surface area, an interior node with the area
    ``V_i / h`` of its nodal volume ``V_i`` (mm^3) over the mean surface edge ``h`` (mm),
    so the wall's penalty stiffness per node is of the same order inside as on the
    surface.  None when ``chest_wall_contact`` is off or the body has no fixed node."""

    if not config.chest_wall_contact or not body.fixed.any():
        return None
    surf_nodes, surf_areas, eps = _surface_contact(body, config)
    X = body.points
    e = X[body.tets]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0]),
                           e[:, 3] - e[:, 0])) / 6.0
    areas = np.bincount(body.tets.reshape(-1), weights=np.repeat(vol / 4.0, 4),
                        minlength=len(X)) / mean_edge_length(X, body.surface)
    areas[surf_nodes] = surf_areas
    nodes = np.flatnonzero(~body.fixed & (areas > 0))
    wall = RigidPlate(name="chest-wall", origin=(float(X[:, 0].min()), 0.0, 0.0),
                      normal=(1.0, 0.0, 0.0), e1=(0.0, 1.0, 0.0))
    return PlateContact(wall, X, nodes, areas[nodes], config=replace(config, friction=0.0),
                        penalty=eps)


def behind_chest_wall(points: np.ndarray, u: np.ndarray, fixed: np.ndarray,
                      *, over_mm: float = 1.0) -> tuple[float | None, int | None]:
    """How far the deformed body lies behind the chest-wall plane: ``(depth_mm, nodes)``.

    The plane is the one :func:`chest_wall` uses, ``x_cw = min_i X_i`` (model frame, ``x``
    posterior -> anterior; the chest-wall nodes of a model cut from an MRI lie within
    0.3 mm of it).  With ``x_i = X_i + u_i``,

    .. math::

        \\mathrm{depth} = \\max\\bigl(0, \\max_i (x_{cw} - x_{i,x})\\bigr),

    and ``nodes`` counts the nodes more than ``over_mm`` behind it.  Tissue there would be
    inside the torso: the paper's model (fixed chest wall, no wall contact) lets the tissue
    pinched by a plate's rounded edge go there.  ``(None, None)`` for a body without
    chest-wall nodes (no wall to be behind)."""
    if not np.any(fixed):
        return None, None
    x_cw = float(np.min(points[:, 0]))
    behind = x_cw - (points[:, 0] + u[:, 0])
    return max(0.0, float(behind.max())), int(np.count_nonzero(behind > over_mm))


def _surface_contact(body: BodySetup, config: ContactConfig
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """Contact candidates of the body: its free surface nodes (:attr:`BodySetup.surface`),
    their tributary areas (mm^2) and the automatic normal penalty (MPa/mm)."""
    X = body.points
    nodes = np.unique(body.surface)
    if body.clamped:
        nodes = nodes[~body.fixed[nodes]]
    if len(nodes) == 0:
        raise ConfigError("model has no free surface node: contact needs outer triangles")
    eps = automatic_penalty(config, young_mpa=body.young_mpa,
                            h_mm=mean_edge_length(X, body.surface))
    return nodes, tributary_areas(X, body.surface)[nodes], eps


def make_plates(body: BodySetup, protocol: Protocol, *, config: ContactConfig,
                u: np.ndarray | None = None) -> tuple[dict[str, PlateContact], Any]:
    """The lower and upper :class:`PlateContact` of a protocol, placed around the body as
    displaced by ``u`` (N, 3) mm (None: the reference shape)."""
    from regtrack.virtual.frames import plate_frame

    frame = plate_frame(protocol.view, body.side, angle_deg=protocol.angle_deg)
    X = body.points
    x = X if u is None else X + np.asarray(u, float).reshape(X.shape)
    nodes, areas, eps = _surface_contact(body, config)
    geo = protocol.plates
    problem = edge_wedge_problem(geo.posterior_edge_mm, geo.edge_radius_mm, config,
                                 fixed=body.fixed.any())
    if problem:
        raise ConfigError(f"protocol '{protocol.name}' [plates]: {problem}")
    s_edge = float(X[:, 0].min()) + geo.posterior_edge_mm  # the chest-wall plane of chest_wall()
    n = frame.normal
    over = X[nodes, 0] >= s_edge
    if not over.any():
        raise ConfigError(f"plates: no surface node anterior to the plate edge x = "
                          f"{s_edge:.1f} mm; lower [plates] posterior_edge_mm")
    h = x[nodes] @ n
    lo = float(h[over].min()) - geo.clearance_mm
    hi = float(h[over].max()) + geo.clearance_mm
    plates = {}
    for name, normal, height in (("lower", n, lo), ("upper", -n, hi)):
        pl = RigidPlate(name=name, origin=height * n, normal=normal, e1=frame.e_x,
                        s_range=(s_edge, np.inf), edge_radius=geo.edge_radius_mm)
        if geo.window_mm and name == geo.window_plate:
            centre = body.target if body.target is not None else X[nodes][over].mean(axis=0)
            pl = replace(pl, window=_opening(pl, centre, geo.window_mm))
        for _ in range(50):  # back off until the rounded edge clears the base behind it too
            short = geo.clearance_mm - float(pl.query(x[nodes]).gap.min())
            if short <= 1e-9:
                break
            pl = pl.translated(-(short + 1e-9) * pl.normal)
        plates[name] = PlateContact(pl, X, nodes, areas, config=config, penalty=eps)
    log.info("plates: normal %s, chest-wall edge x = %.1f mm, eps_N = %.3g MPa/mm",
             np.round(n, 3).tolist(), s_edge, eps)
    return plates, frame


def edge_wedge_problem(posterior_edge_mm: float, edge_radius_mm: float, config: ContactConfig,
                       *, fixed: bool = True) -> str | None:
    """Why a plate edge ``posterior_edge_mm`` (mm anterior to the chest-wall plane) of
    radius ``edge_radius_mm`` cannot be used with ``config``'s chest wall, or None: with
    the wall contact on, ``0 < e <= r`` puts the rounded edge in front of the wall at an
    acute angle (module docstring)."""
    e, r = float(posterior_edge_mm), float(edge_radius_mm)
    if not (config.chest_wall_contact and fixed and 0.0 < e <= r):
        return None
    angle = 90.0 - np.degrees(np.arcsin(e / r))
    return (f"posterior_edge_mm = {e:g} puts the plates' rounded edge (edge_radius_mm = {r:g}) "
            f"{e:g} mm in front of the chest wall, where it meets the wall at {angle:.0f} deg and "
            "pinches the breast base (the contact cannot converge there); use posterior_edge_mm "
            f"<= 0 (the flat face reaches the wall) or > {r:g} (the edge clears it)")


def _opening(plate: RigidPlate, centre: np.ndarray, size_mm) -> tuple[float, float, float, float]:
    """The window ``(s0, s1, t0, t1)`` (plate-local mm) of size ``size_mm`` = [along e_x,
    across], centred on the projection of ``centre`` on the face; moved anteriorly, when the
    lesion lies near the chest wall, to start 1 mm in front of the plate's chest-wall edge
    (an opening must lie inside the face)."""
    s, t, _ = plate.to_local(centre[None])[0]
    w, h = (float(v) for v in size_mm)
    s0 = max(s - w / 2.0, plate.s_range[0] + 1.0)
    if s0 > s - w / 2.0:
        log.info("plate %s: opening moved %.1f mm anteriorly to clear the chest-wall edge",
                 plate.name, s0 - (s - w / 2.0))
    return (s0, s0 + w, t - h / 2.0, t + h / 2.0)


def skin_barrier(body: BodySetup, config: ContactConfig):
    """The outer surface's self-contact barrier (:class:`.selfcontact.SkinBarrier`) of
    ``body``: its outer triangles (:attr:`BodySetup.surface`) with their nodes' tributary
    areas, the plates' automatic normal penalty as its stiffness and ``[contact]
    self_contact_gap_mm`` as its reach; None when that is 0.

    The reference configuration must be stress free, so no node may start within the reach
    of a triangle outside its 2-ring.  Where the model's outer surface already comes closer
    to itself than the reach (a crease the segmentation kept tight), the reach becomes half
    that distance, logged, so the same setting holds on every model.  Raises
    :class:`ConfigError` when a node lies on such a triangle (the surface touches itself:
    the mesh is not a valid solid)."""
    from regtrack.mechanics.selfcontact import SkinBarrier

    if config.self_contact_gap_mm <= 0:
        return None
    X = np.asarray(body.points, float)
    eps = automatic_penalty(config, young_mpa=body.young_mpa, h_mm=mean_edge_length(X, body.surface))
    areas = tributary_areas(X, body.surface)
    bar = SkinBarrier(X, body.surface, areas, kappa=eps, dhat=config.self_contact_gap_mm)
    closest = bar.check_reference()
    if not np.isfinite(closest):
        return bar
    if closest <= 1e-6 * config.self_contact_gap_mm:
        raise ConfigError(f"[contact] self_contact_gap_mm: the model's outer surface touches "
                          f"itself (a node {closest:.2g} mm from a triangle outside its 2-ring); "
                          "re-mesh the model (regtrack mesh) or set it to 0")
    log.info("self-contact: the model's outer surface comes %.3g mm close to itself, under "
             "[contact] self_contact_gap_mm = %g; the barrier's reach is %.3g mm",
             closest, config.self_contact_gap_mm, 0.5 * closest)
    return SkinBarrier(X, body.surface, areas, kappa=eps, dhat=0.5 * closest)
