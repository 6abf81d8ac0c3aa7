"""MRI -> mammogram: where does a point or region of the prone MRI appear in each view?

A point ``q`` (LPS, mm) is taken to the model frame (:class:`AnatomicalFrame.to_model`),
located in the reference (prone MRI) tet mesh (element ``e``, barycentric ``lambda``), and
carried to the compressed configuration of each view by the finite-element deformation,
``x' = sum_k lambda_k x'_{e,k}`` (exact for the P1 mesh).  It is then projected on the
plate, aligned and converted to pixels (:class:`~regtrack.tracking.viewmap.ViewMap`).

A region (the model's tumour, or the voxels of a label of the MRI label map) is tracked
by its *mass centroid*: mass is conserved, so the centroid of the deformed region is
``sum_e V_e c'_e / sum_e V_e`` with the reference volumes ``V_e`` and the deformed
element centroids ``c'_e`` (for voxel sets: the mean of the mapped voxel centres).  Its
projected outline is also given.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from regtrack.errors import TrackingError
from regtrack.model.types import TUMOUR, BreastModel
from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.locate import Location, TetLocator
from regtrack.tracking.uncertainty import inplane_shift
from regtrack.tracking.viewmap import ViewMap

log = logging.getLogger(__name__)


@dataclass
class ViewPrediction:
    """Predicted position of a tracked point/region centroid in one real mammogram.

    ``xy_mm`` is in the real canonical frame (mm; chest wall left), ``px`` the (row, col)
    of the DICOM's own pixel grid (None without pixel information), ``sigma_mm`` the
    1-sigma radius of :mod:`regtrack.tracking.uncertainty` (None without its model) and
    ``terms_mm`` its four terms.
    """

    view: str
    xy_mm: np.ndarray
    px: np.ndarray | None
    sigma_mm: float | None
    terms_mm: dict
    virtual_mm: np.ndarray
    deformed_mm: np.ndarray
    outline_mm: np.ndarray | None = None
    truth_distance_mm: float | None = None
    sigma_px: float | None = None

    @property
    def outline_centroid_mm(self) -> np.ndarray | None:
        """Area centroid (mm) of the projected outline (the metrics' convention)."""
        if self.outline_mm is None:
            return None
        from regtrack.registration.geometry import polygon

        c = polygon(self.outline_mm).centroid
        return np.array([c.x, c.y])

    def to_dict(self) -> dict:
        oc = self.outline_centroid_mm
        return {
            "view": self.view, "xy_mm": self.xy_mm.tolist(),
            "px_rc": None if self.px is None else self.px.tolist(),
            "sigma_mm": self.sigma_mm, "sigma_px": self.sigma_px,
            "uncertainty_terms_mm": self.terms_mm,
            "virtual_mm": self.virtual_mm.tolist(), "deformed_model_mm": self.deformed_mm.tolist(),
            "outline_centroid_mm": None if oc is None else oc.tolist(),
            "outline_mm": None if self.outline_mm is None else self.outline_mm.tolist(),
            "truth_distance_mm": self.truth_distance_mm,
        }


@dataclass
class MriTrack:
    """Result of tracking an MRI point or region into every view."""

    kind: str                     # "point", "tumour", "label"
    description: str
    reference_mm: np.ndarray      # (3,) model frame, reference (prone MRI) configuration
    lps_mm: np.ndarray            # (3,) the same in LPS
    views: dict[str, ViewPrediction] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    n_points: int = 1

    def to_dict(self) -> dict:
        return {"kind": self.kind, "description": self.description, "n_points": self.n_points,
                "reference_model_mm": self.reference_mm.tolist(), "lps_mm": self.lps_mm.tolist(),
                "views": {v: p.to_dict() for v, p in self.views.items()}, "notes": self.notes}


def locate_points(model: BreastModel, points_model, *, locator: TetLocator | None = None,
                  max_outside_mm: float = 2.0,
                  what: str = "MRI point") -> tuple[Location, list[str]]:
    """Locate model-frame points in the reference mesh; snap those just outside.

    Raises
    ------
    TrackingError
        A point farther than ``max_outside_mm`` from the meshed breast.
    """
    loc_ = locator or TetLocator(model.points, model.tets)
    pts = np.atleast_2d(np.asarray(points_model, float))
    loc = loc_.locate(pts)
    notes: list[str] = []
    out = ~loc.inside
    if out.any():
        snapped, dist = loc_.snap(pts[out])
        far = dist > max_outside_mm
        if far.all() or (len(pts) == 1 and far.any()):
            k = int(np.flatnonzero(out)[np.argmin(dist)])
            lps = model.frame.to_patient(pts[k])
            raise TrackingError(
                f"{what} {_fmt(lps)} (LPS mm) lies outside the breast model ({dist.min():.1f} mm "
                f"from the mesh; tolerance {max_outside_mm:g} mm): give a point inside the "
                "segmented breast (the model is cut at the chest wall), in LPS mm")
        idx = np.flatnonzero(out)
        keep = idx[~far]
        loc.element[keep] = snapped.element[~far]
        loc.bary[keep] = snapped.bary[~far]
        if (~far).any():
            notes.append(f"{int((~far).sum())} {what}(s) up to {dist[~far].max():.2f} mm outside "
                         "the mesh were snapped onto it")
        if far.any():
            notes.append(f"{int(far.sum())} of {len(pts)} {what}s lie outside the breast model "
                         f"(> {max_outside_mm:g} mm) and were left out")
        for n in notes:
            log.warning(n)
    return loc, notes


def _fmt(p) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in np.asarray(p, float).reshape(-1)) + ")"


def predict(model: BreastModel, view: ViewMap, reference: np.ndarray, deformed: np.ndarray, *,
            outline: np.ndarray | None = None, truth_mm=None) -> ViewPrediction:
    """Project one model point of ``view`` into the real mammogram: ``reference`` (3,) its
    prone MRI position and ``deformed`` (3,) its compressed one (mm, model frame), with the
    1-sigma radius of the view's uncertainty model."""
    v = view.to_virtual(deformed[None])[0]
    xy = view.inplane.to_real(v)
    sigma, terms, sp = None, {}, None
    if view.uncertainty is not None:
        shift = inplane_shift(view.frame, reference, deformed, model.points[model.nipple],
                              view.positions[model.nipple])
        s, t = view.uncertainty.at(xy, shift)
        sigma, terms = float(s[0]), t[0]
        sp = None if view.pixels is None else sigma / view.pixels.mean_spacing
    px = None if view.pixels is None else view.pixels.mm_to_px(xy)
    td = None if truth_mm is None else float(np.linalg.norm(xy - np.asarray(truth_mm, float)))
    return ViewPrediction(view.view, xy, px, sigma, terms, v, np.asarray(deformed, float),
                          outline, td, sp)


def track_mri_point(model: BreastModel, views: dict[str, ViewMap], point_lps, *,
                    config: TrackingConfig | None = None, locator: TetLocator | None = None,
                    truth: dict | None = None) -> MriTrack:
    """Predicted position of an MRI point (LPS, mm) in every view.

    Parameters
    ----------
    model : BreastModel
        Reference (prone MRI) mesh.
    views : dict
        ``{"CC": ViewMap, "MLO": ViewMap}`` (any subset).
    point_lps : (3,) float
        The point (mm, DICOM patient frame LPS).
    truth : dict, optional
        ``{view: (2,) real canonical mm}``: distance to the prediction is reported.
    """
    cfg = config or TrackingConfig()
    lps = np.asarray(point_lps, float).reshape(3)
    if not np.isfinite(lps).all():
        raise TrackingError(f"MRI point {list(point_lps)} is not finite: give three numbers "
                            "(LPS mm) with --mri-point X Y Z")
    ref = model.frame.to_model(lps)
    loc, notes = locate_points(model, ref[None], locator=locator, max_outside_mm=cfg.max_outside_mm)
    res = MriTrack("point", f"MRI point {_fmt(lps)} LPS mm", ref, lps, notes=notes)
    for name, vm in views.items():
        x = loc.interpolate(model.tets, vm.positions)[0]
        res.views[name] = predict(model, vm, ref, x, truth_mm=(truth or {}).get(name))
    return res


def region_outline(view: ViewMap, tets: np.ndarray) -> np.ndarray | None:
    """Outline (real canonical mm) of the projection of a deformed tet region."""
    import shapely
    from shapely.geometry import Polygon

    from regtrack.virtual.surface import boundary_faces

    faces = boundary_faces(tets, view.positions)
    if len(faces) == 0:
        return None
    xy = view.to_real(view.positions.reshape(-1, 3))
    tri = [Polygon(t) for t in xy[faces]]
    tri = [t for t in tri if t.area > 1e-12]
    if not tri:
        return None
    u = shapely.union_all(tri)
    geom = max(getattr(u, "geoms", [u]), key=lambda g: g.area)
    return np.asarray(geom.exterior.coords)[:-1]


def track_tumour(model: BreastModel, views: dict[str, ViewMap], *, tumour: int = 0,
                 truth: dict | None = None) -> MriTrack:
    """Predicted position of the model's tumour (mass centroid + outline) in every view.

    ``tumour`` = k >= 1 selects the k-th tumour (``model.tumour_id``), 0 all of them.
    """
    sel = model.region == TUMOUR
    if tumour:
        sel &= model.tumour_id == tumour
    if not sel.any():
        have = sorted(set(model.tumour_id[model.region == TUMOUR].tolist()))
        raise TrackingError(f"the model has no tumour {tumour or ''} (tumour ids present: "
                            f"{have or 'none'}); choose --label tumour[:K] from those, or track "
                            "a point with --mri-point")
    tets = model.tets[sel]
    vol = np.abs(model.tet_volumes()[sel])
    w = vol / vol.sum()
    ref = w @ model.points[tets].mean(axis=1)
    name = "tumour" if not tumour else f"tumour {tumour}"
    res = MriTrack("tumour", f"MRI {name} ({int(sel.sum())} tets, {vol.sum():.0f} mm^3), mass "
                   "centroid", ref, model.frame.to_patient(ref), n_points=int(sel.sum()))
    for v, vm in views.items():
        x = w @ vm.positions[tets].mean(axis=1)
        res.views[v] = predict(model, vm, ref, x, outline=region_outline(vm, tets),
                               truth_mm=(truth or {}).get(v))
    return res


def track_points_region(model: BreastModel, views: dict[str, ViewMap], points_lps, *,
                        description: str, config: TrackingConfig | None = None,
                        truth: dict | None = None) -> MriTrack:
    """Track a set of MRI points of equal mass (e.g. the voxel centres of a label, LPS mm)
    by their mean: the mass centroid of the region."""
    cfg = config or TrackingConfig()
    pts = np.atleast_2d(np.asarray(points_lps, float))
    if len(pts) == 0:
        raise TrackingError(f"{description}: no voxels; check the label value (case.toml "
                            "[mri] labels map)")
    loc, notes = locate_points(model, model.frame.to_model(pts), max_outside_mm=cfg.max_outside_mm,
                               what="voxel")
    loc = loc.subset(loc.inside)
    ref = loc.interpolate(model.tets, model.points).mean(axis=0)
    res = MriTrack("label", description, ref, model.frame.to_patient(ref), notes=notes,
                   n_points=len(loc.element))
    for v, vm in views.items():
        x = loc.interpolate(model.tets, vm.positions)
        res.views[v] = predict(model, vm, ref, x.mean(axis=0), truth_mm=(truth or {}).get(v))
    return res
