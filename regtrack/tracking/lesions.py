"""The MRI lesion(s) predicted on each real mammogram: what ``regtrack run`` reports.

Tracking mode (no tumour outline on the mammograms) and paper mode (outlines given) both
make this prediction from a registration on the **breast outline and nipple only**
(:math:`\\theta_p = \\theta_{p,b}`, :func:`regtrack.tracking.viewmap.breast_alignment`), so that it never uses the
answer: in paper mode the distance to the annotated outline (``error_mm``) is then an
honest measure of the tracking error, beside the paper's :math:`d_T` (which aligns on the
tumour too).

Per lesion (each tumour of the model, :func:`predict_lesions`):

* the centroid: the lesion's mass centroid carried by the finite-element deformation
  (:func:`regtrack.tracking.mri_to_view.track_tumour`), projected and registered;
* the outline: the projected outline of its deformed tetrahedra, registered;
* a 1-sigma radius (mm): the uncertainty model of every prediction
  (:class:`regtrack.tracking.uncertainty.PredictionUncertainty`), the same that
  ``regtrack track`` states for an MRI point or region.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.uncertainty import PredictionUncertainty, inplane_shift

log = logging.getLogger(__name__)


@dataclass
class LesionPrediction:
    """One MRI lesion predicted on one real mammogram (mm of the real canonical frame).

    ``centroid_px`` is the (row, col) of the DICOM's own grid; ``terms_mm`` the four
    uncertainty terms (:func:`regtrack.tracking.uncertainty.prediction_sigma`); ``error_mm`` the distance from the predicted
    centroid to the area centroid of the annotated outline paired with the lesion (paper
    mode; None in tracking mode and for a lesion no outline is paired with),
    ``annotated_mm`` that centroid; ``mri_lps_mm`` the lesion's volume centroid in
    the MRI (DICOM patient frame, LPS mm); ``nipple_mm`` / ``nipple_px`` the nipple on the
    mammogram, the centre of the registration's rotation; ``on_image`` the fraction of the
    predicted outline's area that lies on the image (:func:`on_image_fraction`; None where
    the image's extent is not known).
    """

    view: str
    lesion: int
    centroid_mm: np.ndarray
    centroid_px: np.ndarray | None
    outline_mm: np.ndarray | None
    sigma_mm: float
    terms_mm: dict
    theta_deg: float
    theta_sigma_deg: float
    distance_from_nipple_mm: float
    inplane_shift_mm: float
    error_mm: float | None = None
    annotated_mm: np.ndarray | None = None
    outline_px: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    mri_lps_mm: np.ndarray | None = None
    nipple_mm: np.ndarray | None = None
    nipple_px: np.ndarray | None = None
    on_image: float | None = None

    def to_dict(self) -> dict:
        def arr(a):
            return None if a is None else np.asarray(a, float).tolist()
        return {"view": self.view, "lesion": self.lesion, "centroid_mm": arr(self.centroid_mm),
                "centroid_px_rc": arr(self.centroid_px), "sigma_mm": self.sigma_mm,
                "uncertainty_terms_mm": self.terms_mm, "theta_p_b_deg": self.theta_deg,
                "theta_sigma_deg": self.theta_sigma_deg,
                "distance_from_nipple_mm": self.distance_from_nipple_mm,
                "inplane_shift_mm": self.inplane_shift_mm, "error_mm": self.error_mm,
                "annotated_centroid_mm": arr(self.annotated_mm),
                "outline_mm": arr(self.outline_mm), "outline_px_rc": arr(self.outline_px),
                "mri_lps_mm": arr(self.mri_lps_mm), "nipple_mm": arr(self.nipple_mm),
                "nipple_px_rc": arr(self.nipple_px), "on_image_fraction": self.on_image,
                "notes": self.notes}


def predict_lesions(model, *, view: str, positions, virtual, real, alignment, D: float | None,
                    sigma_D: float, config: TrackingConfig | None = None) -> list[LesionPrediction]:
    """Every tumour of ``model`` predicted on the ``real`` mammogram of ``view``.

    Parameters
    ----------
    model : BreastModel
        Reference (prone MRI) mesh with its tumour region(s).
    positions : (N, 3) float
        Deformed node positions of the view's simulation (mm).
    virtual : VirtualMammogram
        Its projection (plate frame and point source).
    real : MammogramView
        The real view (pixel frame; annotated outlines, if any, for ``error_mm``).
    alignment : Alignment
        A breast-only registration (:func:`regtrack.tracking.viewmap.breast_alignment`).
    D, sigma_D : float
        Compression degree of the simulation and its 1-sigma uncertainty (-).
    """
    from regtrack.model.types import TUMOUR
    from regtrack.registration.align import image_extent
    from regtrack.tracking.mri_to_view import region_outline
    from regtrack.tracking.viewmap import InPlane, PixelFrame, ViewMap

    cfg = config or TrackingConfig()
    sel = model.region == TUMOUR
    if not sel.any():
        return []
    ids = np.where(model.tumour_id > 0, model.tumour_id, 1)
    unc = PredictionUncertainty.from_alignment(alignment, real, D=D, sigma_D=sigma_D, config=cfg)
    vm = ViewMap(view, np.asarray(positions, float), virtual.frame,
                 InPlane.from_alignment(alignment), PixelFrame.from_view(real), virtual.source,
                 unc.residual, real, unc)
    nip = vm.inplane.nipple
    nip_px = None if vm.pixels is None else vm.pixels.mm_to_px(nip)
    vol = np.abs(model.tet_volumes())
    extent = image_extent(real)
    out = []
    for k in np.unique(ids[sel]):
        m = sel & (ids == k)
        tets = model.tets[m]
        w = vol[m] / vol[m].sum()
        ref = w @ model.points[tets].mean(axis=1)
        x = w @ vm.positions[tets].mean(axis=1)
        xy = vm.to_real(x[None])[0]
        outline = region_outline(vm, tets)
        shift = float(inplane_shift(virtual.frame, ref, x, model.points[model.nipple],
                                    vm.positions[model.nipple])[0])
        sig, terms = unc.at(xy, shift)
        r = float(np.linalg.norm(xy - nip))
        px = None if vm.pixels is None else vm.pixels.mm_to_px(xy)
        opx = None if (vm.pixels is None or outline is None) else vm.pixels.mm_to_px(outline)
        lps = model.frame.to_patient(ref[None])[0]
        frac = None if extent is None else on_image_fraction(outline, xy, extent)
        out.append(LesionPrediction(view, int(k), xy, px, outline, float(sig[0]), terms[0],
                                    float(alignment.theta_p), unc.theta_sigma_deg, r, shift,
                                    outline_px=opx, notes=image_notes(frac, xy, extent),
                                    mri_lps_mm=lps, nipple_mm=nip, nipple_px=nip_px,
                                    on_image=frac))
    _score_against_outlines(out, real.tumour_contours)
    return out


#: The note of a lesion predicted wholly off the detector (beyond the image's chest-wall
#: edge, or past a side the positioning left out).
OUTSIDE_IMAGE = "outside the image: this mammogram does not show the lesion"

#: The note of a lesion whose predicted outline crosses the image's edge.
PARTLY_OUTSIDE = "partly beyond the image edge: {pct} of its projected area on this mammogram"

#: Appended to :data:`PARTLY_OUTSIDE` where the predicted centroid is off the image: the
#: visible part's centre is then not the lesion's centre.
CENTROID_OFF = "; its centroid lies off the image"


def on_image_fraction(outline_mm, centroid_mm, extent) -> float:
    """Fraction (0-1) of a predicted lesion's projected area that lies on the image.

    ``outline_mm`` is the predicted outline and ``centroid_mm`` its centroid in the real
    view's canonical frame (mm from the image's corner, x from the chest-wall edge, y
    down); ``extent`` the image's (width, height) in mm
    (:func:`regtrack.registration.align.image_extent`).  The outline's area is clipped to
    the rectangle ``[0, width] x [0, height]``.  A lesion without an outline with an area
    (too small to project one) counts as a point: 1 on the image, 0 off it.
    """
    from shapely.geometry import box

    from regtrack.registration.geometry import has_area, polygon

    w, h = (float(v) for v in extent)
    if outline_mm is not None and has_area(outline_mm):
        g = polygon(np.asarray(outline_mm, float))
        if g.area > 0.0:
            return float(min(1.0, g.intersection(box(0.0, 0.0, w, h)).area / g.area))
    return float(_inside(centroid_mm, extent))


def _inside(xy, extent) -> bool:
    """Whether the point ``xy`` (mm) lies on the image ``[0, width] x [0, height]``."""
    x, y = np.asarray(xy, float)
    w, h = (float(v) for v in extent)
    return bool(0.0 <= x <= w and 0.0 <= y <= h)


def image_notes(fraction: float | None, centroid_mm, extent) -> list[str]:
    """The notes on where a predicted lesion lies against the image's edges: none where
    it lies wholly on the image (or the extent is not known), :data:`OUTSIDE_IMAGE` where
    no part of it does, else :data:`PARTLY_OUTSIDE` with the share on the image."""
    if fraction is None or fraction >= 1.0:
        return []
    if fraction <= 0.0:
        return [OUTSIDE_IMAGE]
    pct = ("under 1 %" if fraction < 0.01 else "over 99 %" if fraction > 0.99
           else f"{100.0 * fraction:.0f} %")
    return [PARTLY_OUTSIDE.format(pct=pct) + ("" if _inside(centroid_mm, extent) else CENTROID_OFF)]


def _score_against_outlines(lesions: list[LesionPrediction], outlines) -> None:
    """Paper mode: each predicted lesion's ``error_mm`` against the area centroid of the
    annotated outline paired with it (the pairs of least total centroid distance,
    :func:`regtrack.registration.geometry.pair_points`); a lesion that no outline is left
    for (the image does not show it, or it was not outlined) keeps ``error_mm`` None."""
    from regtrack.registration.geometry import area_centroid, pair_points

    if not outlines or not lesions:
        return
    ref = [area_centroid(np.asarray(c, float)) for c in outlines]
    for j, k in pair_points([p.centroid_mm for p in lesions], ref):
        lesions[j].annotated_mm = ref[k]
        lesions[j].error_mm = float(np.linalg.norm(lesions[j].centroid_mm - ref[k]))
