"""One tracking request on a case: what ``regtrack track`` computes.

:func:`track_case` takes an opened case (:func:`regtrack.tracking.session.open_case`) and
any of: an MRI point (LPS mm), a label (``"tumour"``, ``"tumour:K"`` or a label value of
the MRI label map), points marked on the real CC/MLO mammograms (DICOM ``(row, col)``).
It returns a :class:`TrackResult` (JSON-ready with :meth:`TrackResult.to_dict`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from regtrack.errors import TrackingError
from regtrack.tracking.cc_to_mlo import (ContourPrediction, SegmentPrediction, most_likely,
                                         track_view_contour, track_view_point)
from regtrack.tracking.mri_to_view import (MriTrack, track_mri_point, track_points_region,
                                           track_tumour)
from regtrack.views import VIEWS

log = logging.getLogger(__name__)

OTHER = dict(zip(VIEWS, reversed(VIEWS)))  # the other view of each


@dataclass
class TrackResult:
    """Everything one ``regtrack track`` call predicts (mm, px, degrees)."""

    case_id: str
    views: dict[str, dict] = field(default_factory=dict)   # registration + pixel frame per view
    mri: MriTrack | None = None
    segments: list[SegmentPrediction] = field(default_factory=list)
    contours: dict[str, ContourPrediction] = field(default_factory=dict)  # source view -> region
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "case_id": self.case_id,
            "frames": {
                "mm": "real mammogram, canonical frame: x from the chest wall to the nipple, y "
                      "down (medial for CC, infero-medial for MLO); the centre of canonical "
                      "full-resolution pixel (0, 0) at (0, 0) mm",
                "px_rc": "(row, col) of the DICOM's own (stored) pixel grid",
                "reference_model_mm": "model frame of the prone MRI (origin nipple, x anterior, "
                                      "y superior, z patient right)",
                "lps_mm": "DICOM patient frame of the MRI",
                "sigma_mm": "1-sigma radius: registration residual, rotation, model and nipple "
                            "terms in quadrature (regtrack.tracking.uncertainty), the same as "
                            "the lesions of `regtrack run`",
            },
            "views": self.views,
            "mri": None if self.mri is None else self.mri.to_dict(),
            "segments": [s.to_dict() for s in self.segments],
            "contours": {v: {"target_view": OTHER[v], **c.to_dict()}
                         for v, c in self.contours.items()},
            "notes": self.notes,
        }


def parse_label(label: str) -> tuple[str, int]:
    """``"tumour"`` -> ("tumour", 0); ``"tumour:2"`` -> ("tumour", 2); ``"-3"`` -> ("label", -3)."""
    s = str(label).strip().lower()
    if s in ("tumour", "tumor"):
        return "tumour", 0
    if s.startswith(("tumour:", "tumor:")):
        k = s.split(":", 1)[1]
        if k.isdigit() and int(k) >= 1:
            return "tumour", int(k)
    else:
        try:
            return "label", int(s)
        except ValueError:
            pass
    raise TrackingError(f"--label {label!r}: use 'tumour' (every tumour of the model), "
                        "'tumour:K' (the K-th, K >= 1) or an integer label value of the MRI "
                        "label map (e.g. -3)")


def _label_points(session, value: int) -> np.ndarray:
    from regtrack.imaging.readers import read_label_map

    lab = read_label_map(session.case.mri.labels)
    ijk = np.argwhere(lab.data == value)
    if len(ijk) == 0:
        present = sorted(np.unique(lab.data).tolist())
        raise TrackingError(f"{session.case.mri.labels}: label value {value} is not in the label "
                            f"map (values present: {present}); choose --label from those")
    return lab.index_to_world(ijk)


def track_case(session, *, mri_point=None, label: str | None = None,
               view_points: dict | None = None, truth: dict | None = None,
               view_points_mm: bool = False, view_contours: dict | None = None) -> TrackResult:
    """Run the requested tracking on an opened case.

    Parameters
    ----------
    session : TrackingSession
    mri_point : (3,) float, optional
        MRI point, LPS mm.
    label : str, optional
        ``"tumour"``, ``"tumour:K"`` or an integer label value of the MRI label map.
    view_points : dict, optional
        ``{"CC": (row, col), "MLO": (row, col)}`` marked on the real mammograms (DICOM
        grid; mm of the canonical frame when ``view_points_mm``); each gives a curve in
        the other view.
    truth : dict, optional
        ``{view: (2,) real canonical mm}`` of the true lesion, for the distances reported.
    view_contours : dict, optional
        ``{"CC": (K, 2) (row, col)}``: a contour marked on a real view; gives the region
        (convex hull of the vertices' curves) in the other view.

    Raises
    ------
    TrackingError
        Nothing requested, or an invalid request (see the functions called).
    """
    if mri_point is None and label is None and not view_points and not view_contours:
        raise TrackingError("nothing to track: give --mri-point X Y Z, --label tumour, "
                            "--cc-point ROW COL or --mlo-point ROW COL")
    cfg, model = session.config, session.model
    res = TrackResult(session.case.id)
    for v, vm in session.views.items():
        res.views[v] = {"registration": vm.inplane.to_dict(),
                        "pixel_spacing_mm": (None if vm.pixels is None
                                             else vm.pixels.spacing.tolist()),
                        "dicom_shape": None if vm.pixels is None else vm.pixels.shape,
                        "mammogram": None if vm.pixels is None else vm.pixels.source,
                        "plate_angle_deg": vm.frame.angle_deg,
                        "projection": "orthogonal" if vm.source is None else "point source"}
    if mri_point is not None:
        res.mri = track_mri_point(model, session.views, mri_point, config=cfg,
                                  locator=session.locator, truth=truth)
    elif label is not None:
        kind, value = parse_label(label)
        if kind == "tumour":
            res.mri = track_tumour(model, session.views, tumour=value, truth=truth)
        else:
            res.mri = track_points_region(model, session.views, _label_points(session, value),
                                          description=f"MRI label {value} (voxel centres)",
                                          config=cfg, truth=truth)
    lesions = model.tumour_centroids()
    for src_name, point in (view_points or {}).items():
        src = session.view(src_name)
        dst = session.view(OTHER[src.view])
        seg = track_view_point(model, src, dst, point, pixels=not view_points_mm, config=cfg,
                               truth_mm=(truth or {}).get(dst.view),
                               src_locator=session.view_locator(src.view))
        if res.mri is not None:
            most_likely(seg, res.mri.reference_mm, truth_mm=(truth or {}).get(dst.view),
                        lesion=res.mri.description)
        elif lesions:
            # the known MRI tumour nearest to the ray (in the reference configuration)
            def gap(t: int) -> float:
                return float(np.min(np.linalg.norm(seg.reference_mm - lesions[t], axis=1)))
            k = min(lesions, key=gap)
            most_likely(seg, lesions[k], truth_mm=(truth or {}).get(dst.view),
                        lesion=f"MRI tumour {k} (mass centroid)")
        res.segments.append(seg)
    for src_name, contour in (view_contours or {}).items():
        src = session.view(src_name)
        res.contours[src.view] = track_view_contour(model, src, session.view(OTHER[src.view]),
                                                    contour, pixels=not view_points_mm, config=cfg)
    return res
