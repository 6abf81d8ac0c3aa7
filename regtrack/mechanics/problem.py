"""The discrete problem: reference geometry, materials, sparsity pattern, and the
evaluation of the internal force (tissue + skin) and its consistent tangent.

Plain P1 (``formulation = "p1"``) is exactly the peers' displacement tet4 with one
quadrature point.  The default ``"p1-anp"`` is the average-nodal-pressure tetrahedron
(Bonet & Burton 1998; Bonet, Marriott & Hassan 2001): the volumetric energy is taken at
the nodes, per (node, material group) ``g``,

    W_vol = sum_g V_g K_g / 2 (J_g - 1)^2,   J_g = v_g / V_g,
    v_g = sum_{e around g} v_e / 4,          V_g = sum_{e around g} V_e / 4,

which removes volumetric locking of linear tets; it is variational, so its exact
tangent ``K_loc + B^T diag(K_g / V_g) B`` (``B = dv_g/du``; ``K_loc`` the deviatoric +
``p d2v`` part) is symmetric.  Condensed, that tangent couples 2-rings of nodes; the
solver instead factorises the equivalent *augmented* 1-ring system

    [ K_loc   B^T      ] [du]   [-R]
    [ B      -diag(V_g/K_g)] [dp] = [ 0]

whose ``du`` is exactly the condensed Newton correction (eliminate ``dp``) but whose
factorisation is about 2.4x cheaper (measured, pipelines/bench_mechanics.py).
Units: mm, N, MPa.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numba import njit

from regtrack.errors import ConfigError, InputFileError
from regtrack.mechanics import assembly, membrane, p2, parallel, tissue
from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.materials import (G_SCALE, ElementMaterials, SkinMaterial, TissueStiffness,
                                          element_materials, skin_material, tissue_stiffness)
from regtrack.mechanics.support import WallSupport, wall_support
from regtrack.model.types import BreastModel

#: Absolute floor (N) of a force reference, so that an unloaded state still has one: a
#: micronewton, six orders below a breast's weight, and far above the rounding level of
#: an unloaded residual (about 1e-12 N on a 10 mm box moved rigidly; a floor of 1e-9 N
#: asked 1e-13 N of it, which some CPUs' rounding never reached).
FORCE_FLOOR_N = 1e-6

log = logging.getLogger(__name__)


@dataclass
class Problem:
    """Everything precomputed for a mesh + config; see :func:`build_problem`."""

    model: BreastModel
    config: MechanicsConfig
    X: np.ndarray
    tets: np.ndarray
    G: np.ndarray  # (E, 4, 3) for P1; (E, Q, 10, 3) for P2
    V: np.ndarray  # (E,) volumes for P1; (E, Q) quadrature weights (mm^3) for P2
    mats: ElementMaterials
    skin: np.ndarray
    skin_G: np.ndarray
    skin_A0: np.ndarray
    skin_mat: SkinMaterial | None
    pattern: assembly.Pattern
    tet_base: np.ndarray
    skin_pos: np.ndarray
    groups: assembly.AnpGroups | None
    body_weight: np.ndarray  # (N,) N per (m/s^2): sum rho V_e / 4 * 1e-9
    fixed_dofs: np.ndarray
    layout: assembly.SystemLayout
    t_setup: float = 0.0
    tissue_c1: TissueStiffness | None = None  # c1 of the tissue elements (tissue_model), summary
    parts: list[parallel.Part] | None = None  # the element kernel's threads (P1, P1-ANP)
    support: WallSupport | None = None  # the sliding chest wall's layer (None: clamped)
    support_pos: np.ndarray | None = None  # positions of its (y, z) diagonal entries in the pattern
    self_contact: Any = None  # the outer surface's barrier (.selfcontact.SkinBarrier; None: off)

    @property
    def n_nodes(self) -> int:
        return len(self.X)

    @property
    def n_dofs(self) -> int:
        return 3 * len(self.X)

    @property
    def formulation(self) -> str:
        return self.config.formulation


def dof_nodes(problem: Problem) -> np.ndarray:
    """Mesh node of each unknown of the system matrix (:func:`system_matrix`): ``3 p + k``
    -> ``p``; an ANP pressure ``3 N + g`` -> the node of its group ``g``.  The linear
    solver orders the unknowns node by node with it (:func:`.linsolve.node_ordering`)."""
    nodes = np.repeat(np.arange(problem.n_nodes, dtype=np.int64), 3)
    g = problem.groups
    if g is None:
        return nodes
    # a group's members are (element, local node) pairs of one node: the first one names it
    return np.concatenate([nodes, problem.tets.reshape(-1)[g.members[g.mptr[:-1]]].astype(np.int64)])


def _add_corner_forces(f: np.ndarray, cells: np.ndarray, fe: np.ndarray) -> None:
    """``f[cells[:, a]] += fe[:, a]`` for each corner ``a`` in turn, the elements in order
    (:func:`scatter_add` on the flat dofs): the sums of the three ``np.add.at`` calls it
    replaces, in their order (0.3 against 1.7 ms for the benchmark hemisphere's 4,490 skin
    triangles).  ``f`` (N, 3) C-contiguous, changed in place."""
    flat = f.reshape(-1)
    if not np.shares_memory(flat, f):
        raise ValueError("f must be C-contiguous (forces are added in place)")
    pos = (3 * cells.T[:, :, None] + np.arange(3)).reshape(-1)
    scatter_add(flat, pos, np.ascontiguousarray(fe.transpose(1, 0, 2)).reshape(-1))


@njit(cache=True, nogil=True)
def _anp_pressure(of, V, Je, vol0, kappa):
    """ANP group volume ratios ``J_g = sum_(e, i in g) V_e J_e / 4 / V_g`` (G,) and each
    element's pressure ``p_e = mean_i kappa_g (J_g - 1)`` over its four corners' groups
    (E,).  The sums run in the order of the numpy code they replace (``np.bincount`` over
    the flat corners, ``mean(axis=1)`` left to right then / 4), so the values are the same
    to the bit; 0.2 against 1.35 ms on the benchmark hemisphere."""
    ng = vol0.shape[0]
    vg = np.zeros(ng)
    for e in range(of.shape[0]):
        w = V[e] * Je[e] / 4.0
        for i in range(4):
            vg[of[e, i]] += w
    Jg = np.empty(ng)
    pg = np.empty(ng)
    for g in range(ng):
        Jg[g] = vg[g] / vol0[g]
        pg[g] = kappa[g] * (Jg[g] - 1.0)
    p = np.empty(of.shape[0])
    for e in range(of.shape[0]):
        p[e] = (pg[of[e, 0]] + pg[of[e, 1]] + pg[of[e, 2]] + pg[of[e, 3]]) / 4.0
    return Jg, p


@njit(cache=True)
def scatter_add(data, pos, vals):
    """``data[pos] += vals`` with repeated positions accumulated."""
    for i in range(pos.shape[0]):
        data[pos[i]] += vals[i]


def build_problem(model: BreastModel, config: MechanicsConfig | None = None, *,
                  wall_layer_mm: float = 0.0) -> Problem:
    """Precompute geometry, per-element materials and the fixed tangent pattern.

    ``wall_layer_mm``: the chest-wall nodes lie on the wall on a layer that thick
    (:mod:`.support`: held in ``x``, tangentially by the layer's shear stiffness until
    the plates hold the breast); 0 clamps them.

    Raises :class:`InputFileError` for inverted/degenerate tetrahedra and
    :class:`ConfigError` for an unknown formulation.
    """
    t0 = time.perf_counter()
    config = config or MechanicsConfig()
    X = np.ascontiguousarray(model.points, float)
    tets = np.ascontiguousarray(model.tets, np.int64)
    quadratic = config.formulation == "p2"
    if quadratic != (tets.shape[1] == 10) or tets.shape[1] not in (4, 10):
        raise ConfigError(
            f"[mechanics] formulation = {config.formulation!r} does not fit a mesh of {tets.shape[1]}-node "
            "tetrahedra: use 'p2' with tet10 meshes (regtrack.mechanics.p2.model_to_p2 converts a tet4 "
            "model) and 'p1-anp'/'p1' with tet4 meshes")
    if quadratic and config.skin_enabled:
        raise ConfigError("[mechanics] formulation = 'p2' has no skin membrane: set skin_enabled = false")
    if quadratic:
        G, W, Nq = p2.reference_geometry(X, tets)
        V = W.sum(axis=1)
        bad_q = np.any(W <= 0, axis=1)
        V = np.where(bad_q, -np.abs(V), V)
    else:
        G, V = tissue.reference_geometry(X, tets)
        W = Nq = None
    if np.any(V <= 0):
        bad = int(np.argmin(V))
        raise InputFileError(f"model: {int(np.sum(V <= 0))} tetrahedra with non-positive volume "
                             f"(e.g. element {bad}, V = {V[bad]:.3g} mm^3); re-mesh or fix the orientation")
    tissue_k = tissue_stiffness(model.region, model.tissue_label, V, config)
    mats = element_materials(model.region, config, tissue_k)
    use_skin = config.skin_enabled and len(model.skin) > 0
    skin = np.ascontiguousarray(model.skin if use_skin else np.zeros((0, 3), np.int64), np.int64)
    sG, sA = membrane.reference_geometry(X, skin) if use_skin else (np.zeros((0, 3, 2)), np.zeros(0))
    groups = None
    adj = assembly.node_adjacency(len(X), [tets, skin])
    pattern = assembly.build_pattern(adj)
    if config.formulation == "p1-anp":
        groups = assembly.anp_groups(tets, V, mats.kappa, mats.group, len(X))
    tet_base = assembly.element_bases(pattern, tets)
    skin_pos = _skin_positions(pattern, skin)
    if quadratic:  # consistent body force: sum_q W_q N_a(q) rho (corner shares are negative)
        wa = np.einsum("eq,qa->ea", W, Nq) * mats.rho[:, None]
        w = np.bincount(tets.reshape(-1), weights=wa.reshape(-1), minlength=len(X)) * G_SCALE
    else:
        w = np.bincount(tets.reshape(-1), weights=np.repeat(mats.rho * V / 4.0, 4), minlength=len(X)) * G_SCALE
    support = wall_support(X, tets, model.fixed, c1_mpa=tissue_k.mean_kpa * 1e-3, layer_mm=wall_layer_mm)
    held = np.arange(1) if support is not None else np.arange(3)  # x only when the wall slides
    fixed_dofs = (3 * np.flatnonzero(model.fixed)[:, None] + held).reshape(-1)
    layout = assembly.system_layout(pattern, tets, groups)
    prob = Problem(model, config, X, tets, G, V if W is None else W, mats, skin, sG, sA,
                   skin_material(config) if use_skin else None, pattern, tet_base, skin_pos, groups, w,
                   fixed_dofs, layout, support=support,
                   support_pos=None if support is None else pattern.dof_positions(*support.entries()[:2]))
    if not quadratic:
        threads = parallel.thread_count(config.solver.assembly_threads)
        prob.parts = parallel.node_partition(len(X), tets, threads)
    prob.t_setup = time.perf_counter() - t0
    prob.tissue_c1 = tissue_k
    log.debug("problem: %d nodes, %d tets, %d skin triangles, %s, nnz %d, setup %.2f s",
              len(X), len(tets), len(skin), config.formulation, pattern.nnz, prob.t_setup)
    return prob


def _skin_positions(pattern: assembly.Pattern, skin: np.ndarray) -> np.ndarray:
    if len(skin) == 0:
        return np.zeros(0, np.int64)
    base = assembly.element_bases(pattern, skin)  # (T, 3, 3)
    rs = pattern.rowstride[skin]  # (T, 3)
    i = np.arange(3)
    # (t, a, i, b, k) -> base[t, a, b] + i * rs[t, a] + k
    pos = (base[:, :, None, :, None] + i[None, None, :, None, None] * rs[:, :, None, None, None]
           + i[None, None, None, None, :])
    return pos.reshape(-1)


def body_force(problem: Problem, g_ms2: np.ndarray) -> np.ndarray:
    """Nodal gravity load (3N,) in N for an acceleration ``g_ms2`` (m/s^2, model frame)."""
    return (problem.body_weight[:, None] * np.asarray(g_ms2, float)[None, :]).reshape(-1)


@njit(cache=True)
def _scatter_b(out, b_pos, b_dest, bt_dest, dv):
    """``out[b_pos] += bvals`` for the ANP ``B`` values ``bvals[e, i, a, k] = dv[e, a, k] / 4``
    (:attr:`Evaluation.bvals`), without forming them, then ``B^T``'s entries copied from
    ``B``'s (``out[bt_dest] = out[b_dest]``).  Same values, same order of summation as two
    :func:`scatter_add` calls over ``b_pos`` and ``bt_pos``, at less than half the cost
    (10.5 against 4 ms on the 48k-tetrahedron benchmark hemisphere)."""
    j = 0
    for e in range(dv.shape[0]):
        for i in range(4):
            for a in range(4):
                for k in range(3):
                    out[b_pos[j]] += 0.25 * dv[e, a, k]
                    j += 1
    for s in range(b_dest.shape[0]):
        out[bt_dest[s]] = out[b_dest[s]]


@dataclass
class Evaluation:
    """Internal force (3N,) N, tangent CSR values (local part) or None, stored energy (N mm),
    inverted count, and for ANP (with the tangent) ``dv`` (E, 4, 3), the derivative of each
    element's current volume, from which ``B = dv_g/du`` follows (:attr:`bvals`)."""

    f: np.ndarray
    data: np.ndarray | None
    energy: float
    n_inverted: int
    dv: np.ndarray | None = None

    @property
    def bvals(self) -> np.ndarray | None:
        """Values of ``B = dv_g/du`` (E*48,) in layout order: ``B[g(e, i), dofs of e] +=
        dv_e / 4`` for each local node ``i``."""
        if self.dv is None:
            return None
        dv = self.dv
        return np.broadcast_to(0.25 * dv[:, None, :, :], (len(dv), 4, 4, 3)).reshape(-1)


def evaluate(problem: Problem, u: np.ndarray, *, want_k: bool = True, project: bool = False) -> Evaluation:
    """Tissue + skin (+ the chest-wall layer, :mod:`.support`) internal force and
    (optionally) tangent at displacement ``u``: the consistent tangent, or with
    ``project`` each tetrahedron's projected onto the positive semi-definite cone
    (:func:`.tissue.tet_kernel`; P1 and ANP only)."""
    ev = _evaluate_body(problem, u, want_k, project)
    s = problem.support
    if s is not None and np.isfinite(ev.energy):
        ev.f += s.gradient(u)
        ev.energy += s.energy(u)
        if ev.data is not None and want_k:
            ev.data[problem.support_pos] += s.entries()[2]
    return ev


def chest_wall_reaction(problem: Problem, u: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The force (3,) N the chest wall exerts on the body, from the residual ``R``
    (N, 3) at ``u``: the residual of the held dofs (the support reactions) plus the
    layer's spring forces ``-k u`` (:mod:`.support`)."""
    f = np.zeros(problem.n_dofs)
    f[problem.fixed_dofs] = np.asarray(R, float).reshape(-1)[problem.fixed_dofs]
    if problem.support is not None:
        f -= problem.support.gradient(u)
    return f.reshape(-1, 3).sum(axis=0)


def force_balance(problem: Any, u: np.ndarray, r: np.ndarray, g_ms2: np.ndarray,
                  contribs: list, tol: float) -> dict:
    """The global force balance of a converged state: the resultant of the residual over
    the free dofs, ``|sum_free R|`` (N), which equals the sum of the chest-wall reaction,
    the plate forces and the weight, against the largest of those loads (N).

    The convergence test bounds ``||R||_2`` over the free dofs, which bounds the resultant
    only to ``sqrt(free nodes)`` times it, since many small nodal errors of one sign add
    up; this is the check of the sum itself.  ``ok`` is False when the relative imbalance
    exceeds ``tol`` (the caller passes ``stall_force_tol``)."""
    held = np.zeros(np.size(r), bool)
    held[problem.fixed_dofs] = True
    imbalance = float(np.linalg.norm(np.where(held.reshape(-1, 3), 0.0, r).sum(axis=0)))
    loads = [float(np.linalg.norm(chest_wall_reaction(problem, u, r))),
             float(np.linalg.norm(problem.body_weight.sum() * np.asarray(g_ms2, float)))]
    for c in contribs:
        loads.append(float(np.linalg.norm(c.nodal_forces(u)[0].sum(axis=0))))
    load = max(*loads, FORCE_FLOOR_N)
    rel = imbalance / load
    return {"imbalance_N": imbalance, "load_N": load, "relative": rel, "tol": float(tol),
            "ok": bool(rel <= tol)}


def constraint_positions(problem: Problem, dofs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Value positions of the system matrix (fixed layout) zeroed (the rows and columns of
    the constrained ``dofs``) and set to one (their diagonal): ``M.data[zero] = 0;
    M.data[diag] = 1`` replaces them by the identity without a new sparsity analysis."""
    lay = problem.layout
    smask = np.zeros(lay.n, bool)
    smask[dofs] = True
    rows = np.repeat(smask, np.diff(lay.indptr))
    zero = rows | smask[lay.indices]
    diag = problem.pattern.dof_positions(dofs, dofs)
    return zero, (diag if lay.k_pos is None else lay.k_pos[diag])


def _evaluate_body(problem: Problem, u: np.ndarray, want_k: bool, project: bool) -> Evaluation:
    x = problem.X + np.asarray(u, float).reshape(-1, 3)
    m = problem.mats
    if problem.formulation == "p2":
        return _evaluate_p2(problem, x, want_k)
    Je = tissue.jacobians(x, problem.tets, problem.G, problem.parts)
    if np.any(Je <= 0) or not np.all(np.isfinite(Je)):
        return Evaluation(np.full(problem.n_dofs, np.nan), None, np.inf, int(np.sum(~(Je > 0))))
    grp = problem.groups
    if grp is not None:
        Jg, p = _anp_pressure(grp.of, problem.V, Je, grp.vol0, grp.kappa)
        dp = np.zeros_like(p)
        e_vol = float(np.sum(grp.vol0 * grp.kappa / 2.0 * (Jg - 1.0) ** 2))
    else:
        p = m.kappa * (Je - 1.0)
        dp = m.kappa
        e_vol = float(np.sum(problem.V * m.kappa / 2.0 * (Je - 1.0) ** 2))
    f = np.zeros((problem.n_nodes, 3))
    data = np.zeros(problem.pattern.nnz) if want_k else np.zeros(1)
    dv = np.empty((len(problem.tets), 4, 3))
    ee = np.empty(len(problem.tets))
    args = (x, problem.tets, problem.G, problem.V, m.c1, p, dp, want_k, project, f, data, problem.tet_base,
            problem.pattern.rowstride, dv, ee)
    bad = sum(parallel.run_parts(tissue.tet_kernel, args, problem.parts))
    e_dev = tissue.ordered_sum(ee)
    dv_b = dv if (want_k and grp is not None) else None  # B = dv_g/du (Evaluation.bvals)
    energy = e_dev + e_vol
    if problem.skin_mat is not None:
        try:
            fe, Ke, e_skin = membrane.membrane_forces(x, problem.skin, problem.skin_G, problem.skin_A0,
                                                      problem.skin_mat, want_k=want_k)
        except FloatingPointError:
            return Evaluation(np.full(problem.n_dofs, np.nan), None, np.inf, -1)
        _add_corner_forces(f, problem.skin, fe)
        if want_k:
            scatter_add(data, problem.skin_pos, Ke.reshape(-1))
        energy += e_skin
    return Evaluation(f.reshape(-1), data if want_k else None, energy, int(bad), dv_b)


def _evaluate_p2(problem: Problem, x: np.ndarray, want_k: bool) -> Evaluation:
    f = np.zeros((problem.n_nodes, 3))
    data = np.zeros(problem.pattern.nnz) if want_k else np.zeros(1)
    energy, bad = p2.tet10_kernel(x, problem.tets, problem.G, problem.V, problem.mats.c1, problem.mats.kappa,
                                  want_k, f, data, problem.tet_base, problem.pattern.rowstride)
    if bad:
        return Evaluation(np.full(problem.n_dofs, np.nan), None, np.inf, int(bad))
    return Evaluation(f.reshape(-1), data if want_k else None, float(energy), 0)


def internal_force(problem: Problem, u: np.ndarray) -> np.ndarray:
    """Tissue + skin internal force (N, 3) in N at displacement ``u`` (N, 3) mm."""
    return evaluate(problem, u, want_k=False).f.reshape(-1, 3)


def reaction_forces(problem: Problem, u: np.ndarray, *, gravity_ms2=None) -> np.ndarray:
    """Residual ``f_int - f_ext`` (N, 3) in N at ``u`` (N, 3) mm, ``f_ext`` the weight under
    ``gravity_ms2`` (m/s^2; None: none): at constrained nodes the force the supports exert
    on the body; at free nodes about zero after convergence (without contact)."""
    R = evaluate(problem, u, want_k=False).f
    if gravity_ms2 is not None:
        R = R - body_force(problem, gravity_ms2)
    return R.reshape(-1, 3)


def tangent(problem: Problem, u: np.ndarray):
    """Consistent tangent (3N, 3N) CSR (N/mm) of the internal force at ``u``."""
    ev = evaluate(problem, u, want_k=True)
    if ev.data is None:
        raise FloatingPointError("inverted elements at this displacement")
    K = problem.pattern.matrix(ev.data)
    grp = problem.groups
    if grp is None:
        return K
    lay = problem.layout
    B = sp.csr_matrix((ev.bvals, (lay.b_rows, lay.b_cols)), shape=(grp.n_groups, problem.n_dofs))
    return (K + B.T @ sp.diags(grp.kappa / grp.vol0) @ B).tocsr()


def system_matrix(problem: Problem, ev: Evaluation, data: np.ndarray | None = None) -> sp.csr_matrix:
    """The matrix the solver factorises: the tangent (P1) or the augmented ANP system."""
    lay = problem.layout
    kd = ev.data if data is None else data
    if problem.groups is None:
        return problem.pattern.matrix(kd)
    out = np.zeros(len(lay.indices))
    out[lay.k_pos] = kd
    _scatter_b(out, lay.b_pos, lay.b_dest, lay.bt_dest, ev.dv)
    out[lay.d_pos] = -problem.groups.vol0 / problem.groups.kappa
    m = sp.csr_matrix((out, lay.indices, lay.indptr), shape=(lay.n, lay.n), copy=False)
    m.has_sorted_indices = True
    return m
