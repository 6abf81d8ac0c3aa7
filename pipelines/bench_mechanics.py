"""Benchmark of the mechanics core on gmsh hemispheres (R = 50 mm, chest wall fixed).

For each mesh size and formulation it prints: nodes, tets, setup time (pattern and
maps), assembly of residual + tangent, residual only, PARDISO analysis (once per
pattern), factorisation + solve, one Newton iteration (assembly + factor/solve),
Newton iterations of a standing-gravity step (with how many factorisations and how
many GMRES solves preconditioned by a re-used factorisation), and the peak resident memory of the
process (each size runs in its own subprocess, so the peak is per size).

    .venv/bin/python pipelines/bench_mechanics.py            # ~2k, ~10k, ~50k nodes
    .venv/bin/python pipelines/bench_mechanics.py --lc 5.5 2.9

Timings are wall-clock medians of 3 repetitions; on a shared machine compare ratios
within one run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time


def one(lc: float, formulation: str, with_step: bool = True) -> dict:
    import resource

    import numpy as np

    from regtrack.mechanics import problem as P
    from regtrack.mechanics import solver as S
    from regtrack.mechanics.config import MechanicsConfig
    from regtrack.mechanics.linsolve import LinearSolver
    from regtrack.mechanics.meshes import hemisphere_model

    t = time.perf_counter()
    model = hemisphere_model(50.0, lc, tumour_radius=6.0)
    t_mesh = time.perf_counter() - t
    t = time.perf_counter()
    pr = S.build_problem(model, MechanicsConfig(formulation=formulation))
    t_setup = time.perf_counter() - t
    u = np.zeros_like(pr.X)
    P.evaluate(pr, u)  # JIT warm-up (cached on disk after the first run)

    def med(f, n=3):
        ts = []
        for _ in range(n):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts))

    t_asm = med(lambda: P.evaluate(pr, u, want_k=True))
    t_res = med(lambda: P.evaluate(pr, u, want_k=False))
    ev = P.evaluate(pr, u)
    A = P.system_matrix(pr, ev)
    cons = S._Constraints(pr, pr.fixed_dofs)
    A.data[cons.zero] = 0.0
    A.data[cons.diag] = 1.0
    b = np.ones(A.shape[0])
    ls = LinearSolver(reuse_factorisation=False)
    ls.solve(A, b, symmetric=True)
    t_an = ls.time_analysis
    t_fs = med(lambda: ls.solve(A, b, symmetric=True))
    ls.release()
    out = {"gravity_iterations": "-", "gravity_increments": "-", "gravity_step_s": "-",
           "gravity_factorisations": "-", "gravity_krylov_solves": "-", "gravity_t_assembly_s": "-",
           "gravity_t_solve_s": "-"}
    if with_step:
        t = time.perf_counter()
        _, st = S.solve_step(pr, u, gravity=lambda s: np.array([0.0, -9.81 * s, 0.0]), step_name="gravity")
        out = {"gravity_iterations": st.iterations, "gravity_increments": st.increments,
               "gravity_step_s": time.perf_counter() - t, "gravity_factorisations": st.factorisations,
               "gravity_krylov_solves": st.krylov_solves, "gravity_t_assembly_s": st.t_assembly,
               "gravity_t_solve_s": st.t_solve}
    return {**out, "lc": lc, "formulation": formulation, "nodes": pr.n_nodes, "tets": len(pr.tets),
            "system": A.shape[0], "nnz": int(A.nnz), "mesh_s": t_mesh, "setup_s": t_setup,
            "assembly_s": t_asm, "residual_s": t_res, "analysis_s": t_an, "factor_solve_s": t_fs,
            "newton_iteration_s": t_asm + t_fs,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lc", type=float, nargs="+", default=[5.5, 2.9, 1.65], help="gmsh element sizes (mm)")
    ap.add_argument("--formulations", nargs="+", default=["p1-anp", "p1"])
    ap.add_argument("--no-step-above", type=int, default=30000,
                    help="skip the gravity step for meshes with more nodes than this (time)")
    ap.add_argument("--one", nargs=3, metavar=("LC", "FORM", "STEP"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(float(args.one[0]), args.one[1], args.one[2] == "1")))
        return
    cols = ["formulation", "nodes", "tets", "system", "nnz", "setup_s", "assembly_s", "residual_s", "analysis_s",
            "factor_solve_s", "newton_iteration_s", "gravity_iterations", "gravity_factorisations",
            "gravity_krylov_solves", "gravity_t_assembly_s", "gravity_t_solve_s", "gravity_step_s", "peak_rss_mb"]
    print(" | ".join(cols))
    for lc in args.lc:
        for form in args.formulations:
            est_nodes = 2.0e3 * (5.5 / lc) ** 3  # measured: lc 5.5 mm -> ~2k nodes on R = 50 mm
            step = "1" if est_nodes <= args.no_step_above else "0"
            out = subprocess.run([sys.executable, __file__, "--one", str(lc), form, step], capture_output=True,
                                 text=True)
            if out.returncode != 0:
                print(f"lc={lc} {form}: failed: {out.stderr.strip().splitlines()[-1:]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(" | ".join(f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c]) for c in cols), flush=True)
    print("(times in s, memory in MB; '-': gravity step skipped for size)")


if __name__ == "__main__":
    main()
