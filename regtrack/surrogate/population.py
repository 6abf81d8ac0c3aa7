"""Population surrogate: a new patient's compressed shape from its own geometry, per node.

Issue 56, item 2, after Martínez-Martínez et al. (2017, *Comput. Biol. Med.* 90:116-124),
who trained tree ensembles on per-node features to predict each node's displacement.
Theirs learned one patient's deformations; this one learns across patients: it is fitted
on the simulated compressions of a cohort and predicts the displacement field of a breast
it has never seen, from that breast's reference (prone MRI) mesh alone -- no simulation.

Frame.  Everything is expressed in the view's plate frame
(:func:`regtrack.virtual.frames.plate_frame`) with its origin at the nipple: rows
``e_x`` (posterior -> anterior), ``e_down`` (medial for CC, infero-medial for MLO) and
``n`` (lower -> upper plate).  ``e_down`` and ``n`` are built from the medial unit vector,
so a left breast and the mirror image (``z -> -z``) of a right breast have the same local
coordinates: left and right breasts are comparable without further mirroring.

Features (:data:`FEATURES`, one row per node, mm unless dimensionless):

* ``X``, ``Y``, ``H`` -- the node relative to the nipple along ``e_x``, ``e_down``, ``n``;
* ``depth_frac`` -- ``(X - X_min) / (X_nipple - X_min)``, 0 at the chest wall, 1 at the nipple;
* ``lat_frac`` -- ``(Y - Y_min) / (Y_max - Y_min)`` across the plates' plane;
* ``h_frac`` -- ``(H - H_min) / T0``: the normalised height between the plates' directions,
  which is what the compression acts on;
* ``d_skin``, ``d_wall`` -- distance to the nearest skin node and chest-wall (fixed) node;
* ``col_thick``, ``col_frac``, ``top_gap``, ``bottom_gap`` -- the breast's column along ``n``
  through the node (:func:`line_extent`): its thickness, the node's fraction of it, and how
  far its top / bottom lie inside the breast's extent along ``n`` (how far a plate travels
  before it touches that column: thin columns are compressed less);
* ``row_width``, ``row_frac`` -- the same across the plates' plane (along ``e_down``);
  ``to_front`` -- distance to the anterior skin along ``e_x``;
* ``wall_h_frac``, ``wall_height`` -- where the chest wall's centre sits in the breast's
  height range (fraction of ``T0``) and its extent along ``n``: the fixed base the plates
  squeeze the breast against;
* ``T0`` (extent along ``n``, the uncompressed thickness), ``depth`` (``X_nipple - X_min``),
  ``width`` (extent along ``e_down``), ``volume_ml`` -- the breast's size, one value per patient;
* ``tumour`` -- 1 on nodes of a tumour element (stiffer), else 0.

All are invariant to a rigid translation of the patient (differences and distances only).
``T0`` here is geometric (reference mesh); the simulation's ``T0_mm`` is measured after the
gravity unloading and is not used, since it needs a simulation.

Target.  The displacement per node in the plate frame divided by the patient's ``T0``
(:func:`to_target`); the compression closes the plates by ``D * T0``, so the scaled field is
closer to one population shape.  :func:`from_target` maps a prediction back to mm, model frame.

Mean-shape baseline (:func:`mean_shape_baseline`).  For each node of the new patient, take
its normalised coordinates ``q = (depth_frac, lat_frac, h_frac)``; in each training patient
find the nearest node in ``q``; average those nodes' scaled targets over the training
patients and map back with the new patient's ``T0`` and frame.  It is the average breast's
deformation transferred by normalised position -- what the ensemble must beat to show that
the per-node features carry information beyond the average shape.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from regtrack.model.types import TUMOUR, BreastModel
from regtrack.virtual.frames import plate_frame

FEATURES = ("X", "Y", "H", "depth_frac", "lat_frac", "h_frac", "d_skin", "d_wall",
            "col_thick", "col_frac", "top_gap", "bottom_gap", "row_width", "row_frac",
            "to_front", "wall_h_frac", "wall_height",
            "T0", "depth", "width", "volume_ml", "tumour")
#: Cell (mm) of the grids on which the breast's local extents (columns, rows) are measured.
CELL_MM = 6.0
REGRESSORS = ("extra", "forest")


@dataclass
class NodeFeatures:
    """Per-node features of one patient in one view.

    ``values`` (N, len(FEATURES)); ``rotation`` (3, 3) rows ``e_x, e_down, n`` of the
    plate frame (model -> local); ``T0`` mm, the scale of the target; ``q`` (N, 3)
    the normalised coordinates of the mean-shape baseline."""

    values: np.ndarray
    rotation: np.ndarray
    T0: float
    q: np.ndarray


def line_extent(loc: np.ndarray, axis: int, cell: float = CELL_MM) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest coordinate ``axis`` (mm) of the nodes on the line through each node
    along that axis: the nodes are binned on a ``cell``-mm grid of the two other coordinates
    and each bin takes the extremes over itself and its 8 neighbours (a 3-cell-wide tube)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    other = [k for k in range(3) if k != axis]
    ij = np.floor((loc[:, other] - loc[:, other].min(axis=0)) / cell).astype(int)
    shape = tuple(ij.max(axis=0) + 1)
    lo = np.full(shape, np.inf)
    hi = np.full(shape, -np.inf)
    np.minimum.at(lo, (ij[:, 0], ij[:, 1]), loc[:, axis])
    np.maximum.at(hi, (ij[:, 0], ij[:, 1]), loc[:, axis])
    lo = minimum_filter(lo, size=3, mode="constant", cval=np.inf)
    hi = maximum_filter(hi, size=3, mode="constant", cval=-np.inf)
    return lo[ij[:, 0], ij[:, 1]], hi[ij[:, 0], ij[:, 1]]


def node_features(model: BreastModel, view: str, *, angle_deg: float | None = None) -> NodeFeatures:
    """Features (:data:`FEATURES`) of every node of ``model`` for ``view`` ("CC"/"MLO")."""
    pf = plate_frame(view, model.frame.side, angle_deg=angle_deg)
    R = pf.rotation
    p = model.points
    loc = (p - p[model.nipple]) @ R.T                      # (X, Y, H), mm, nipple at 0
    X, Y, H = loc.T
    lo, hi = loc.min(axis=0), loc.max(axis=0)
    depth = max(float(X[model.nipple] - lo[0]), 1e-9)      # chest wall (min X) -> nipple
    width = max(float(hi[1] - lo[1]), 1e-9)
    T0 = max(float(hi[2] - lo[2]), 1e-9)
    skin_nodes = np.unique(model.skin)
    d_skin = cKDTree(p[skin_nodes]).query(p)[0] if len(skin_nodes) else np.zeros(len(p))
    wall = np.flatnonzero(model.fixed)
    d_wall = cKDTree(p[wall]).query(p)[0] if len(wall) else X - lo[0]
    tumour = np.zeros(len(p))
    tumour[np.unique(model.tets[model.region == TUMOUR])] = 1.0
    volume_ml = float(np.abs(model.tet_volumes()).sum()) / 1000.0
    depth_frac = (X - lo[0]) / depth
    lat_frac = (Y - lo[1]) / width
    h_frac = (H - lo[2]) / T0
    c_lo, c_hi = line_extent(loc, 2)                        # the column along n
    col_thick = np.maximum(c_hi - c_lo, 1e-9)
    r_lo, r_hi = line_extent(loc, 1)                        # the row along e_down
    row_width = np.maximum(r_hi - r_lo, 1e-9)
    _, x_hi = line_extent(loc, 0)                           # the line along e_x
    hw = H[wall] if len(wall) else H[X <= lo[0] + 1e-6]
    ones = np.ones(len(p))
    values = np.column_stack([X, Y, H, depth_frac, lat_frac, h_frac, d_skin, d_wall,
                              col_thick, (H - c_lo) / col_thick, hi[2] - c_hi, c_lo - lo[2],
                              row_width, (Y - r_lo) / row_width, x_hi - X,
                              (hw.mean() - lo[2]) / T0 * ones, (hw.max() - hw.min()) * ones,
                              T0 * ones, depth * ones, width * ones, volume_ml * ones, tumour])
    return NodeFeatures(values, R, T0, np.column_stack([depth_frac, lat_frac, h_frac]))


def to_target(displacement: np.ndarray, nf: NodeFeatures) -> np.ndarray:
    """Model-frame displacement (N, 3) mm -> plate-frame displacement / T0 (dimensionless)."""
    return (np.asarray(displacement, float) @ nf.rotation.T) / nf.T0


def from_target(target: np.ndarray, nf: NodeFeatures) -> np.ndarray:
    """Inverse of :func:`to_target`: (N, 3) scaled plate-frame field -> mm, model frame."""
    return (np.asarray(target, float) * nf.T0) @ nf.rotation


def exam_key(name: str) -> str:
    """Exam of a breast folder: ``exam02R`` and ``exam02`` -> ``exam02`` (an L/R suffix after
    the digits is the other breast of the same exam)."""
    return re.sub(r"(?<=\d)[LR]$", "", name)


def lopo_folds(names: list[str]) -> list[tuple[str, list[int], list[int]]]:
    """Leave-one-patient-out folds ``(exam, train indices, test indices)``; both breasts of
    an exam are left out together, so no fold trains on the other side of its test patient."""
    keys = [exam_key(n) for n in names]
    out = []
    for k in dict.fromkeys(keys):
        test = [i for i, kk in enumerate(keys) if kk == k]
        out.append((k, [i for i in range(len(keys)) if keys[i] != k], test))
    return out


def make_regressor(kind: str = "extra", *, n_estimators: int = 40, min_samples_leaf: int = 3,
                   max_features: float = 1.0, n_jobs: int = 1, seed: int = 0):
    """scikit-learn tree ensemble: ``extra`` (ExtraTreesRegressor, Geurts et al. 2006) or
    ``forest`` (RandomForestRegressor, Breiman 2001); multi-output (the 3 components)."""
    from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor

    cls = {"extra": ExtraTreesRegressor, "forest": RandomForestRegressor}.get(kind)
    if cls is None:
        raise ValueError(f"regressor '{kind}': use one of {', '.join(REGRESSORS)}")
    return cls(n_estimators=n_estimators, min_samples_leaf=min_samples_leaf,
               max_features=max_features, n_jobs=n_jobs, random_state=seed)


@dataclass
class PopulationSurrogate:
    """Tree ensemble from per-node features to the scaled displacement (:func:`to_target`).

    ``columns`` picks the features used (indices into :data:`FEATURES`; default all);
    ``per_patient`` caps the training nodes drawn (uniformly, seeded) from each patient,
    so that every patient weighs the same and a fit stays within seconds.  After a fit /
    predict, ``fit_s``, ``features_s``, ``predict_s`` hold wall seconds and ``fit_cpu_s``,
    ``predict_cpu_s`` (features + ensemble) this process's CPU seconds, the steadier figure
    on a shared host."""

    view: str
    kind: str = "extra"
    per_patient: int | None = 1500
    columns: tuple[int, ...] = tuple(range(len(FEATURES)))
    seed: int = 0
    regressor_options: dict = field(default_factory=dict)
    fit_s: float = float("nan")
    predict_s: float = float("nan")
    features_s: float = float("nan")
    fit_cpu_s: float = float("nan")
    predict_cpu_s: float = float("nan")
    _reg: object = None

    def fit(self, features: list[NodeFeatures], displacements: list[np.ndarray]) -> PopulationSurrogate:
        """Fit on training patients: their features and simulated displacements (N_i, 3) mm."""
        rng = np.random.default_rng(self.seed)
        xs, ys = [], []
        for nf, u in zip(features, displacements):
            idx = np.arange(len(u))
            if self.per_patient is not None and len(idx) > self.per_patient:
                idx = np.sort(rng.choice(idx, self.per_patient, replace=False))
            xs.append(nf.values[idx][:, list(self.columns)])
            ys.append(to_target(u[idx], nf))
        t, c = time.perf_counter(), time.process_time()
        self._reg = make_regressor(self.kind, seed=self.seed, **self.regressor_options)
        self._reg.fit(np.vstack(xs), np.vstack(ys))
        self.fit_s, self.fit_cpu_s = time.perf_counter() - t, time.process_time() - c
        return self

    def predict(self, model: BreastModel, nf: NodeFeatures | None = None) -> np.ndarray:
        """Displacement field (N, 3) mm, model frame, of a new patient.  ``features_s`` records
        the seconds spent on its features (0 when ``nf`` is given), ``predict_s`` those of
        the ensemble and the map back to mm."""
        t, c = time.perf_counter(), time.process_time()
        nf = node_features(model, self.view) if nf is None else nf
        t1 = time.perf_counter()
        u = from_target(self._reg.predict(nf.values[:, list(self.columns)]), nf)
        self.features_s, self.predict_s = t1 - t, time.perf_counter() - t1
        self.predict_cpu_s = time.process_time() - c
        return u

    def importances(self) -> dict[str, float]:
        """Impurity-based feature importances of the fitted ensemble (sum 1)."""
        return {FEATURES[c]: float(v) for c, v in zip(self.columns, self._reg.feature_importances_)}


def mean_shape_baseline(train_features: list[NodeFeatures], train_displacements: list[np.ndarray],
                        nf: NodeFeatures) -> np.ndarray:
    """Mean-shape baseline displacement (N, 3) mm for a patient with features ``nf``: the
    mean over training patients of the scaled target at the nearest node in normalised
    coordinates ``q``, mapped back with this patient's ``T0`` and frame (module docstring)."""
    acc = np.zeros((len(nf.q), 3))
    for f, u in zip(train_features, train_displacements):
        j = cKDTree(f.q).query(nf.q)[1]
        acc += to_target(u, f)[j]
    return from_target(acc / len(train_features), nf)


def nodal_error_summary(predicted: np.ndarray, simulated: np.ndarray) -> dict[str, float]:
    """Median, 95th percentile and maximum (mm) of the per-node Euclidean distance between
    predicted and simulated deformed positions (same reference, so between displacements)."""
    e = np.linalg.norm(np.asarray(predicted, float) - np.asarray(simulated, float), axis=1)
    return {"median_mm": float(np.median(e)), "p95_mm": float(np.percentile(e, 95)),
            "max_mm": float(e.max())}
