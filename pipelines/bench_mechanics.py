"""Benchmark of the mechanics core on gmsh hemispheres (R = 50 mm, chest wall fixed) or meshed cases.

For each mesh size and formulation, in its own subprocess (so the memory peak is per
size), it measures, as wall-clock / process-CPU seconds (the CPU time counts every thread
and does not grow with other jobs on a shared machine; the wall time is what a user
waits):

* ``assembly``: residual + consistent tangent + the system matrix that is factorised,
  on the default threads (``[mechanics.solver] assembly_threads``), and in brackets the
  thread count and the wall time of the same assembly on one thread (medians of 7
  alternated calls);
* ``factor+solve``: PARDISO factorisation (float32 factors, ``precision = "mixed"``,
  node-blocked METIS ordering, ``ordering = "nodes"``) and GMRES to a relative residual
  of 1e-10; ``PARDISO order``: the same with PARDISO's own ordering of the dof graph;
  ``factor+solve dbl``: node ordering, float64 factors; ``analysis``: ordering + symbolic
  analysis (once per sparsity pattern), node ordering / PARDISO's;
* ``re-used solve``: the tangent at the gravity-loaded state solved to 1e-2 (the inexact
  Newton tolerance) on the factors of the unloaded state (GMRES iterations in brackets);
* ``iteration``: ``assembly + factor+solve`` (an iteration that refactorises) and
  ``assembly + re-used solve`` (one that does not);
* the standing-gravity step (9.81 m/s^2, -y) from rest with the default solver options
  and the whole load in one increment (``initial_increment = 1``): increments, Newton
  iterations, factorisations, wall / CPU time;
* peak resident memory of the process (MB).

    .venv/bin/python pipelines/bench_mechanics.py            # ~2k, ~10k, ~50k nodes
    .venv/bin/python pipelines/bench_mechanics.py --lc 5.5 2.9 --formulations p1-anp
    .venv/bin/python pipelines/bench_mechanics.py --model out/exam05/model.vtu --formulations p1-anp

On a shared machine compare ratios within one run.  With other jobs on the cores set
``MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1`` (threads otherwise spin against them).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time


def _timed(f, n: int = 1):
    """Median (wall, cpu) seconds of ``n`` calls of ``f``; returns (wall, cpu, last value)."""
    import numpy as np

    ws, cs, out = [], [], None
    for _ in range(n):
        w, c = time.perf_counter(), time.process_time()
        out = f()
        ws.append(time.perf_counter() - w)
        cs.append(time.process_time() - c)
    return float(np.median(ws)), float(np.median(cs)), out


def one(lc: float, formulation: str, with_step: bool = True, model_path: str = "") -> dict:
    import resource

    import numpy as np

    from regtrack.errors import SolverDidNotConvergeError
    from regtrack.mechanics import problem as P
    from regtrack.mechanics.config import MechanicsConfig, SolverOptions
    from regtrack.mechanics.linsolve import LinearSolver
    from regtrack.mechanics.meshes import hemisphere_model
    from regtrack.mechanics.minimise import minimise_step
    from regtrack.mechanics.problem import constraint_positions

    if model_path:
        from regtrack.model.io import load_model

        model = load_model(model_path)
    else:
        model = hemisphere_model(50.0, lc, tumour_radius=6.0)
    w_setup, c_setup, pr = _timed(lambda: P.build_problem(model, MechanicsConfig(formulation=formulation)))
    u = np.zeros_like(pr.X)
    P.evaluate(pr, u)  # JIT warm-up (cached on disk after the first run)
    zero, diag = constraint_positions(pr, pr.fixed_dofs)

    def system(uu, prob=pr):
        A = P.system_matrix(prob, P.evaluate(prob, uu))
        A.data[zero] = 0.0
        A.data[diag] = 1.0
        return A

    # the same assembly on one thread (assembly_threads = 1), alternated with the default
    pr1 = P.build_problem(model, MechanicsConfig(formulation=formulation,
                                                 solver=SolverOptions(assembly_threads=1)))
    P.evaluate(pr1, u)
    both = [(_timed(lambda: system(u)), _timed(lambda: system(u, pr1)))
            for _ in range(7)]
    w_asm, c_asm = (float(np.median([b[0][i] for b in both])) for i in range(2))
    w_one = float(np.median([b[1][0] for b in both]))
    A = system(u)
    b = np.ones(A.shape[0])
    r = {"lc": lc, "formulation": formulation, "nodes": pr.n_nodes, "tets": len(pr.tets), "system": A.shape[0],
         "nnz": int(A.nnz), "setup": [w_setup, c_setup], "assembly": [w_asm, c_asm],
         "assembly_threads": len(pr.parts or [1]), "assembly_one_thread_wall": w_one}
    nodes = P.dof_nodes(pr)
    # mixed with the node ordering last: its factors precondition the re-used solve
    for name, prec, order in (("double", "double", "nodes"), ("pardiso_order", "mixed", "pardiso"),
                              ("mixed", "mixed", "nodes")):
        ls = LinearSolver(precision=prec, reuse_factorisation=False, ordering=order, dof_nodes=nodes,
                          decoupled=pr.fixed_dofs)
        ls.solve(A, b)  # ordering + analysis (once per pattern) + first factorisation
        r[f"analysis_{name}"] = ls.time_analysis
        w, c, _ = _timed(lambda: ls.solve(A, b), 5 if A.shape[0] < 100_000 else 2)
        r[f"factor_solve_{name}"] = [w, c]
        r[f"factor_nnz_{name}"] = ls.factor_nnz
        if name != "mixed":
            ls.release()
    # the re-use policy's cost ratio (factorisation / GMRES iteration): measured vs estimated
    be = ls.backend
    _, c_it, _ = _timed(lambda: (be.solve(b), A @ b), 10)
    r["cost_ratio"] = [ls.cpu_factor / c_it, ls.cost_ratio]
    # re-used factors of the unloaded state on the tangent of the gravity-loaded state
    w_st = c_st = ug = st = None
    if with_step:
        try:
            w_st, c_st, (ug, st, _) = _timed(lambda: minimise_step(
                pr, u, gravity=lambda s: np.array([0.0, -9.81 * s, 0.0]), n_increments=1,
                step_name="gravity"))
        except SolverDidNotConvergeError as exc:  # a real model's frame need not suit a -y pull
            r["gravity_error"] = str(exc).split(";")[0]
    if ug is not None:
        Ag = system(ug)
        ls.reuse = True
        k0 = ls.krylov_iterations
        w, c, _ = _timed(lambda: ls.solve(Ag, b, rtol=1e-2))
        r["reused_solve"] = [w, c]
        r["reused_gmres_iterations"] = ls.krylov_iterations - k0
        r["gravity"] = {"increments": st.increments, "iterations": st.iterations,
                        "factorisations": st.factorisations, "krylov_solves": st.krylov_solves,
                        "wall": w_st, "cpu": c_st, "u_max_mm": float(np.abs(ug).max())}
    r["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return r


def _fmt(x) -> str:
    return "-" if x is None else f"{x[0]:.2f} / {x[1]:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lc", type=float, nargs="+", default=[5.5, 2.9, 1.65], help="gmsh element sizes (mm)")
    ap.add_argument("--formulations", nargs="+", default=["p1-anp", "p1"])
    ap.add_argument("--no-step-above", type=int, default=100000,
                    help="skip the gravity step for meshes with more nodes than this (time)")
    ap.add_argument("--json", action="store_true", help="print the raw records as JSON lines too")
    ap.add_argument("--model", nargs="+", default=[], help="model .vtu files (regtrack mesh, e.g. a "
                    "Pelicano exam meshed at the defaults) benchmarked instead of the hemispheres")
    ap.add_argument("--one", nargs=4, metavar=("LC", "FORM", "STEP", "MODEL"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(float(args.one[0]), args.one[1], args.one[2] == "1", args.one[3])))
        return
    print("| formulation | nodes | system | assembly | analysis: nodes / PARDISO order | factor+solve "
          "| factor+solve, PARDISO order | factor+solve dbl | re-used solve (GMRES it) "
          "| iteration: refactor / re-use | gravity step: incr, it, fact | gravity step | cost ratio meas. / est. "
          "| peak MB |")
    print("|---" * 14 + "|")
    runs = [(0.0, m) for m in args.model] or [(lc, "") for lc in args.lc]
    for lc, model in runs:
        for form in args.formulations:
            est_nodes = 2.0e3 * (5.5 / lc) ** 3 if lc else 0  # measured: lc 5.5 mm -> ~2k nodes (R = 50 mm)
            step = "1" if est_nodes <= args.no_step_above else "0"
            out = subprocess.run([sys.executable, __file__, "--one", str(lc), form, step, model],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{model or f'lc={lc}'} {form}: failed: {out.stderr.strip().splitlines()[-1:]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            asm, fs, ru = r["assembly"], r["factor_solve_mixed"], r.get("reused_solve")
            it_ref = [asm[0] + fs[0], asm[1] + fs[1]]
            it_re = None if ru is None else [asm[0] + ru[0], asm[1] + ru[1]]
            g = r.get("gravity")
            gi = "-" if g is None else f"{g['increments']}, {g['iterations']}, {g['factorisations']}"
            gt = "-" if g is None else _fmt([g["wall"], g["cpu"]])
            an = f"{r['analysis_mixed']:.2f} / {r['analysis_pardiso_order']:.2f}"
            a1 = f"{_fmt(asm)} ({r['assembly_threads']} thr; 1: {r['assembly_one_thread_wall']:.2f})"
            print(f"| {form} | {r['nodes']} | {r['system']} | {a1} | {an} | {_fmt(fs)} | "
                  f"{_fmt(r['factor_solve_pardiso_order'])} | {_fmt(r['factor_solve_double'])} | {_fmt(ru)} ({r.get('reused_gmres_iterations', '-')}) | "
                  f"{_fmt(it_ref)} ; {_fmt(it_re)} | {gi} | {gt} | {r['cost_ratio'][0]:.0f} / {r['cost_ratio'][1]:.0f} | "
                  f"{r['peak_rss_mb']:.0f} |", flush=True)
            if "gravity_error" in r:
                print(f"  (gravity step: {r['gravity_error']})")
            if args.json:
                print(json.dumps(r))
    print("(seconds as wall / CPU; memory in MB; '-': not run for this size)")


if __name__ == "__main__":
    main()
