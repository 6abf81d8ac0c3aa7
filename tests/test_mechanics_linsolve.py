"""Linear solver: preconditioned GMRES, mixed precision, factorisation re-use, inexact Newton.

Tolerances: the solves are asked for relative residuals of 1e-10; comparisons with an
independent direct solve (SuperLU) allow 1e-7 relative, the condition number of these
small systems (<= ~1e3) times the residual tolerance with margin.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from regtrack.mechanics import problem as P
from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.mechanics.linsolve import LinearSolveError, LinearSolver, right_gmres
from regtrack.mechanics.meshes import box_model
from regtrack.mechanics.minimise import minimise_step
from regtrack.mechanics.problem import constraint_positions

pardiso = pytest.importorskip("pypardiso")


def anp_system(scale: float, seed: int = 0):
    """The augmented ANP system (constraints applied) of a clamped box at a random state."""
    m = box_model((3.0, 2.0, 2.0), (4, 3, 3))
    m.fixed = m.points[:, 2] < 1e-9
    pr = P.build_problem(m, MechanicsConfig(nu=0.49))
    rng = np.random.default_rng(seed)
    u = scale * rng.standard_normal(pr.X.shape)
    u[m.fixed] = 0.0
    A = P.system_matrix(pr, P.evaluate(pr, u))
    zero, diag = constraint_positions(pr, pr.fixed_dofs)
    A.data[zero] = 0.0
    A.data[diag] = 1.0
    return A, rng.standard_normal(A.shape[0])


def relres(A, x, b):
    return np.linalg.norm(A @ x - b) / np.linalg.norm(b)


def test_right_gmres_exact_and_identity_preconditioner():
    rng = np.random.default_rng(1)
    A = sp.random(200, 200, density=0.05, random_state=2) + 10 * sp.identity(200)
    A = A.tocsr()
    b = rng.standard_normal(200)
    lu = spla.splu(A.tocsc())
    x, k = right_gmres(lambda v: A @ v, lu.solve, b, rtol=1e-12, max_iterations=20)
    assert k <= 2 and relres(A, x, b) < 1e-12  # exact preconditioner: one step (+ round-off)
    x, k = right_gmres(lambda v: A @ v, lambda v: v, b, rtol=1e-10, max_iterations=200)
    assert relres(A, x, b) <= 1e-10 and 2 < k < 200  # the residual it reports is the true one


@pytest.mark.parametrize("precision", ["mixed", "double"])
def test_solution_matches_an_independent_direct_solve(precision):
    A, b = anp_system(0.05)
    ref = spla.spsolve(A.tocsc(), b)
    ls = LinearSolver(precision=precision)
    x = ls.solve(A, b)
    assert relres(A, x, b) <= 1e-10
    assert np.linalg.norm(x - ref) <= 1e-7 * np.linalg.norm(ref)
    assert ls.n_factorisations == 1 and ls.n_analyses == 1
    # a float32 factorisation is a near-exact preconditioner: a handful of iterations
    assert ls.krylov_iterations <= (6 if precision == "mixed" else 2)


def test_factorisation_is_reused_until_stale():
    # a nearby state (same random direction, 5 % further): the old factors precondition it in
    # 4 GMRES iterations, within the budget of this small system (cost ratio at its floor, 16)
    A0, b = anp_system(0.002, seed=3)
    A1, _ = anp_system(0.0021, seed=3)
    ls = LinearSolver()
    ls.solve(A0, b)
    x = ls.solve(A1, b, rtol=1e-8)
    assert relres(A1, x, b) <= 1e-8
    assert ls.n_factorisations == 1 and ls.n_krylov_solves == 1 and ls.n_analyses == 1
    assert ls.n_reuse_failures == 0 == ls.krylov_wasted_iterations
    # without re-use every matrix is factorised
    ls2 = LinearSolver(reuse_factorisation=False)
    ls2.solve(A0, b)
    ls2.solve(A1, b, rtol=1e-8)
    assert ls2.n_factorisations == 2 and ls2.n_krylov_solves == 0
    # a GMRES budget of one iteration cannot reach 1e-12 on the old factors: refactorise
    ls3 = LinearSolver(krylov_max=1, precision="double")
    ls3.solve(A0, b)
    x = ls3.solve(A1, b, rtol=1e-12)
    assert relres(A1, x, b) <= 1e-12 and ls3.n_factorisations == 2
    assert ls3.n_reuse_failures == 1 and ls3.krylov_wasted_iterations == 1  # the one iteration


def test_reuse_budget_sets_the_gmres_iterations_before_refactorising():
    """A state 4x further from the factorised one needs 12 GMRES iterations on the old
    factors (measured; the cost ratio of this small system is at its floor, 16).  With the
    default budget of half the cost ratio (8 iterations) the re-use fails after its 8
    iterations and the matrix is refactorised; with a budget of one cost ratio (16) the
    old factors solve it.  Both give the solution."""
    A0, b = anp_system(0.002, seed=3)
    A1, _ = anp_system(0.008, seed=3)
    runs, reuse_its = {}, {}
    for budget in (0.5, 1.0):
        ls = LinearSolver(reuse_budget=budget)
        ls.solve(A0, b)
        k0 = ls.krylov_iterations  # the fresh factorisation's own solve
        x = ls.solve(A1, b, rtol=1e-8)
        assert relres(A1, x, b) <= 1e-8 and ls.cost_ratio == 16.0
        runs[budget], reuse_its[budget] = ls, ls.krylov_iterations - k0
    half, one = runs[0.5], runs[1.0]
    assert half.n_reuse_failures == 1 and half.krylov_wasted_iterations == 8
    assert half.n_factorisations == 2 and half.n_krylov_solves == 0
    assert one.n_reuse_failures == 0 and one.n_factorisations == 1 and one.n_krylov_solves == 1
    assert 8 < reuse_its[1.0] <= 16
    assert LinearSolver().reuse_budget == 0.5


def test_mixed_precision_falls_back_to_double_when_too_inaccurate():
    """With one GMRES iteration allowed, float32 factors (error ~1e-6) cannot reach 1e-10:
    the solver switches to float64 factors for good and still solves.  (1e-10, not 1e-12:
    with MKL 2026.x one iteration on float64 factors gives 1.1e-12 on this system, and
    float32 factors miss even 1e-8.)"""
    A, b = anp_system(0.05)
    ls = LinearSolver(krylov_max=1, krylov_rtol=1e-10)
    x = ls.solve(A, b)
    assert ls.precision == "double" and relres(A, x, b) <= 1e-10


def test_inconsistent_singular_system_raises():
    A = sp.csr_matrix(np.array([[1.0, 1.0], [1.0, 1.0]]))
    with pytest.raises(LinearSolveError):
        LinearSolver().solve(A, np.array([1.0, 0.0]))


def test_inexact_newton_reaches_the_exact_newton_solution():
    """Large shear + compression of a heterogeneous box in one increment: inexact Newton on
    re-used factorisations meets the same stated convergence criteria as exact Newton
    (every direction factorised afresh), with fewer factorisations than iterations, and
    lands on the same equilibrium."""
    m = box_model((3.0, 2.0, 2.0), (3, 2, 2))
    pr = P.build_problem(m, MechanicsConfig(nu=0.49))
    X = pr.X
    bottom, top = np.flatnonzero(X[:, 2] < 1e-9), np.flatnonzero(X[:, 2] > 2 - 1e-9)
    dofs = np.concatenate([(3 * bottom[:, None] + np.arange(3)).ravel(), (3 * top[:, None] + np.arange(3)).ravel()])
    target = np.concatenate([np.zeros(3 * len(bottom)), np.tile([0.4, 0.0, -0.3], len(top))])
    out = {}
    for reuse in (False, True):
        o = SolverOptions(force_tol=1e-10, balance_tol=1e-10, disp_abs_tol_mm=1e-8)
        pr._minimiser_solver = LinearSolver(reuse_factorisation=reuse, dof_nodes=P.dof_nodes(pr),
                                            decoupled=pr.fixed_dofs)  # fresh solver per mode
        out[reuse] = minimise_step(pr, np.zeros_like(X), dirichlet=lambda t: (dofs, t * target),
                                   n_increments=1, options=o)[:2]
    (u_ex, st_ex), (u_in, st_in) = out[False], out[True]
    assert st_in.factorisations < st_in.iterations and st_in.krylov_solves > 0
    assert st_ex.krylov_solves == 0 and st_ex.factorisations > st_ex.iterations
    # both stop with corrections below 1e-8 mm; agreement to a few times that
    assert np.abs(u_in - u_ex).max() <= 1e-7 * np.abs(u_ex).max()
    R = P.reaction_forces(pr, u_in)
    free = np.ones(len(X), bool)
    free[bottom] = free[top] = False
    assert np.linalg.norm(R[free]) <= 1e-9 * np.linalg.norm(R[~free])


def test_reuse_decisions_do_not_depend_on_measured_times(monkeypatch):
    """The factorisation re-use (GMRES budget, staleness) follows the factor size, not the
    clock: with a random CPU clock the counters and the solutions are the same, so a
    Newton path (and a contact run) is reproducible on a loaded machine."""
    import regtrack.mechanics.linsolve as L

    mats = [anp_system(s, seed=3)[0] for s in (0.002, 0.0021, 0.0025, 0.003, 0.005, 0.01, 0.03)]
    _, b = anp_system(0.0)

    def run():
        ls = LinearSolver()
        xs = [ls.solve(A, b, rtol=1e-8) for A in mats]
        return xs, (ls.n_factorisations, ls.n_krylov_solves, ls.krylov_iterations)

    x1, c1 = run()
    rng = np.random.default_rng(7)
    monkeypatch.setattr(L, "_cpu", lambda: float(rng.uniform(0, 100)))
    x2, c2 = run()
    assert c1 == c2 and c1[1] >= 1  # some solves re-used a factorisation
    for a, b_ in zip(x1, x2):
        assert np.array_equal(a, b_)
    assert os.environ.get("MKL_CBWR")  # MKL's reproducible mode is requested


# -- fill-reducing ordering: node-blocked METIS, Dirichlet dofs decoupled -------------------

def _hemisphere_system():
    from regtrack.mechanics.meshes import hemisphere_model

    pr = P.build_problem(hemisphere_model(50.0, 5.5, tumour_radius=6.0), MechanicsConfig())
    u = np.zeros_like(pr.X)
    A = P.system_matrix(pr, P.evaluate(pr, u))
    zero, diag = constraint_positions(pr, pr.fixed_dofs)
    A.data[zero] = 0.0
    A.data[diag] = 1.0
    return pr, A


def test_dof_nodes_name_the_node_of_every_unknown():
    pr, A = _hemisphere_system()
    nodes = P.dof_nodes(pr)
    n3 = pr.n_dofs
    assert len(nodes) == A.shape[0] > n3  # ANP: pressures after the displacements
    assert np.array_equal(nodes[:n3], np.repeat(np.arange(pr.n_nodes), 3))
    g = pr.groups  # every member (element, local node) of a pressure group is that node
    members = np.repeat(np.arange(g.n_groups), np.diff(g.mptr))
    assert np.array_equal(pr.tets.reshape(-1)[g.members], nodes[n3 + members])
    p1 = P.build_problem(box_model((1.0, 1.0, 1.0), (2, 2, 2)), MechanicsConfig(formulation="p1"))
    assert np.array_equal(P.dof_nodes(p1), np.repeat(np.arange(p1.n_nodes), 3))


def test_node_ordering_keeps_each_node_together_and_cuts_the_fill():
    """The order is a permutation with each node's unknowns consecutive; with it and the
    chest-wall dofs decoupled the float32 factor of the 2k-node hemisphere has fewer
    non-zeros than with PARDISO's own ordering of the full pattern (measured 1.83 M against
    2.48 M, ratio 0.74; asserted < 0.9).  An order read with the inverse convention gives
    ~20x the fill (measured at 10k), so the bound also checks the perm convention.  Both
    solve to the asked residual and agree with each other."""
    from regtrack.mechanics.linsolve import node_ordering

    pr, A = _hemisphere_system()
    nodes = P.dof_nodes(pr)
    order = node_ordering(A, nodes)
    assert np.array_equal(np.sort(order), np.arange(A.shape[0]))
    runs = np.flatnonzero(np.diff(nodes[order]) != 0)
    assert len(runs) + 1 == len(np.unique(nodes))  # one run of positions per node
    b = np.random.default_rng(4).standard_normal(A.shape[0])
    own = LinearSolver(ordering="pardiso")
    blocked = LinearSolver(dof_nodes=nodes, decoupled=pr.fixed_dofs)
    x_own = own.solve(A, b)
    x_blk = blocked.solve(A, b)
    assert blocked.time_ordering > 0 and own.time_ordering == 0
    assert relres(A, x_own, b) <= 1e-10 and relres(A, x_blk, b) <= 1e-10
    assert np.linalg.norm(x_blk - x_own) <= 1e-7 * np.linalg.norm(x_own)
    assert blocked.factor_nnz < 0.9 * own.factor_nnz, (blocked.factor_nnz, own.factor_nnz)


def test_decoupled_dofs_in_superlu_and_broken_promise():
    """Decoupled dofs in the SuperLU path (the whole matrix less their couplings), and a
    caller that breaks the promise (couplings of 'decoupled' dofs are not zero): GMRES
    multiplies by the full matrix, so the answer is still right to the tolerance (or the
    solve raises)."""
    A, b = anp_system(0.05)
    n = A.shape[0]
    offdiag = abs(A - sp.diags(A.diagonal()))
    fixed = np.flatnonzero(np.asarray(offdiag.sum(axis=1)).ravel() == 0)  # the identity rows
    assert 0 < len(fixed) < n
    ls = LinearSolver("splu", decoupled=fixed)
    x = ls.solve(A, b)
    assert relres(A, x, b) <= 1e-10
    assert np.linalg.norm(x - spla.spsolve(A.tocsc(), b)) <= 1e-7 * np.linalg.norm(x)
    free = np.setdiff1d(np.arange(n), fixed)[:20]  # 'decoupled' dofs that are not
    liar = LinearSolver(decoupled=free)
    try:
        x = liar.solve(A, b)
    except LinearSolveError:
        return
    assert relres(A, x, b) <= 1e-10


def test_anp_system_matrix_from_dv_equals_the_explicit_b_assembly():
    """system_matrix scatters B = dv_g/du straight from the element volume derivatives
    (no E*48 value array); the result must be bit-for-bit the explicit assembly from
    ``Evaluation.bvals``, and its condensation the exact ANP tangent."""
    m = box_model((3.0, 2.0, 2.0), (4, 3, 3))
    m.fixed = m.points[:, 2] < 1e-9
    pr = P.build_problem(m, MechanicsConfig(nu=0.49))
    u = 0.05 * np.random.default_rng(3).standard_normal(pr.X.shape)
    ev = P.evaluate(pr, u)
    A = P.system_matrix(pr, ev)
    lay = pr.layout
    ref = np.zeros(len(lay.indices))
    ref[lay.k_pos] = ev.data
    P.scatter_add(ref, lay.b_pos, ev.bvals)
    P.scatter_add(ref, lay.bt_pos, ev.bvals)
    ref[lay.d_pos] = -pr.groups.vol0 / pr.groups.kappa
    np.testing.assert_array_equal(A.data, ref)
    # Schur complement of the pressure block = the condensed tangent of problem.tangent
    n3 = pr.n_dofs
    Ad = A.toarray()
    K, Bt, B, D = Ad[:n3, :n3], Ad[:n3, n3:], Ad[n3:, :n3], Ad[n3:, n3:]
    np.testing.assert_allclose(K - Bt @ np.linalg.solve(D, B), P.tangent(pr, u).toarray(),
                               rtol=1e-9, atol=1e-12 * np.abs(K).max())


def test_pattern_key_is_reused_for_views_of_the_layout_and_hashed_otherwise(monkeypatch):
    """The solver recognises the fixed layout through scipy's fresh views of its index
    arrays (no hash per Newton iteration) and still tells patterns apart by content."""
    import hashlib

    A, _ = anp_system(0.01)
    B, _ = anp_system(0.02)
    ls = LinearSolver()
    k1 = ls._key(A)
    k2 = ls._key(B)  # separate problems, separate arrays: hashed, equal by content
    assert A.indices is not B.indices and k1 == k2
    hashes = []
    real = hashlib.blake2b
    monkeypatch.setattr(hashlib, "blake2b", lambda *a, **k: hashes.append(1) or real(*a, **k))
    view = sp.csr_matrix((2 * B.data, B.indices, B.indptr), shape=B.shape, copy=False)
    assert view.indices is not B.indices and np.shares_memory(view.indices, B.indices)
    assert ls._key(view) == k2 and not hashes  # a view of the last layout: no hash
    other = (A + sp.eye(A.shape[0], k=5)).tocsr()
    assert ls._key(other) != k2 and hashes  # another pattern: hashed, another key


def _openblas():
    """threadpoolctl's controller of the loaded OpenBLAS pools (numpy's, scipy's)."""
    from threadpoolctl import ThreadpoolController

    blas = ThreadpoolController().select(internal_api="openblas")
    if not blas.lib_controllers:
        pytest.skip("numpy does not use OpenBLAS here")
    return blas


def _openblas_threads() -> set:
    return {c.num_threads for c in _openblas().lib_controllers}


def test_newton_path_does_not_depend_on_the_openblas_thread_count():
    """numpy's OpenBLAS splits dot products and norms of more than 10,000 entries across its
    threads, each split summing in another order; the solver runs it on one thread
    (``serial_openblas``), so a solve whose vectors are longer than that (4,050 nodes,
    12,150 unknowns) gives bit-identical displacements whatever the thread count outside,
    and the outside setting is restored afterwards.  With the limit removed the two
    solutions differ by 9e-11 mm (checked when the test was written)."""
    blas = _openblas()
    m = box_model((30.0, 30.0, 40.0), (14, 14, 17))
    m.fixed = m.points[:, 2] < 1e-9
    pr = P.build_problem(m, MechanicsConfig(nu=0.49))
    assert pr.n_dofs > 10_000
    inside = []

    def progress(name, t, **info):
        inside.append(_openblas_threads())

    out = []
    for n in (1, 2):
        with blas.limit(limits=n):
            if n == 2 and _openblas_threads() != {2}:
                pytest.skip("OpenBLAS does not take two threads here")
            pr._minimiser_solver = None
            u, st, _ = minimise_step(pr, np.zeros_like(pr.X), n_increments=2, progress=progress,
                                     gravity=lambda t: t * np.array([9.81, 0.0, -9.81]))
            assert _openblas_threads() == {n}  # the caller's setting is back
        out.append(u)
    assert st.iterations >= 4 and np.abs(out[0]).max() > 1.0  # a nonlinear solve, mm-size motion
    assert inside and all(s == {1} for s in inside)
    assert np.array_equal(out[0], out[1]), np.abs(out[0] - out[1]).max()


def test_serial_openblas_blocks_that_overlap_restore_the_setting_when_the_last_one_leaves():
    """Simulations sharing a process (threads of a Dask worker) overlap their blocks out
    of nesting order: the limit must hold until the last block leaves, then the caller's
    setting comes back."""
    from regtrack.mechanics.linsolve import serial_openblas

    with _openblas().limit(limits=2):
        if _openblas_threads() != {2}:
            pytest.skip("OpenBLAS does not take two threads here")
        a, b = serial_openblas(), serial_openblas()
        a.__enter__()
        b.__enter__()
        assert _openblas_threads() == {1}
        a.__exit__(None, None, None)  # the first one leaves while the second still runs
        assert _openblas_threads() == {1}
        b.__exit__(None, None, None)
        assert _openblas_threads() == {2}


def test_mkl_is_located_without_searching_the_environment():
    """_pardiso_function hands pypardiso the library where the mkl wheel installs it, so
    pypardiso skips its recursive search of the environment (0.32 s per process here); the
    solver then works as before.  A fresh interpreter, PYPARDISO_MKL_RT unset."""
    import subprocess
    import sys

    pytest.importorskip("pypardiso")
    code = ("import os; from regtrack.mechanics.direct import _pardiso_function; "
            "from regtrack.mechanics.linsolve import LinearSolver; "
            "_pardiso_function(); import numpy as np, scipy.sparse as sp; "
            "x = LinearSolver('pardiso').solve(sp.identity(5, format='csr') * 2.0, np.ones(5)); "
            "print(os.environ.get('PYPARDISO_MKL_RT', ''), float(x.sum()))")
    env = {k: v for k, v in os.environ.items() if k != "PYPARDISO_MKL_RT"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out[-1] == "2.5"
    import glob

    wheel = glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*"))
    if not wheel:
        pytest.skip("no mkl_rt in <prefix>/lib (not the mkl wheel's layout): pypardiso searched")
    assert len(out) == 2 and out[0] in wheel
