"""Benchmark: the shipped CC and MLO protocols on a ~10,000-node model (issue 5).

Usage::

    .venv/bin/python pipelines/bench_protocols.py [--lc 3.0] [--views cc mlo] [--out DIR]
    .venv/bin/python pipelines/bench_protocols.py --model out/model.vtu   # a meshed case
    .venv/bin/python pipelines/bench_protocols.py --concurrent   # views at the same time

``--concurrent`` runs the views in two processes at the same time, as ``regtrack run``
does on two or more cores (:func:`regtrack.pipeline.workers.simulate_concurrently`); each
view's table is then printed when both are done, and "all views" is the wall-clock time
of the pair.

Prints one table row per protocol step (increments, Newton iterations, augmentations,
line-search trials rejected for inverted elements, assembly / contact / linear-solve /
total seconds), a line for a plate move that converged only on an automatic retry (its
row is the retry's; the failed attempts' time is in the total) and the totals:
wall-clock and the process CPU time (on a shared machine the CPU time is the figure that
does not depend on the other jobs; the wall-clock is what a user waits). Timings depend
on machine load: compare ratios, not absolute figures across runs.  The last line gives
each protocol's time in units of a reference Newton iteration measured on the same model
before and after the runs (:func:`reference_iteration`), a figure that the host's drift
(10-25 % between runs here) does not move. With other jobs on
the CPU, set MKL_NUM_THREADS=1 (PARDISO's threads otherwise spin against them).

Threads and paths: the frictional Newton path (and with it the iteration count) depends on
round-off.  PARDISO in MKL's strict CNR mode (set by :mod:`regtrack.mechanics.linsolve`)
gives bit-identical solutions with 1, 2 or 4 threads (measured on a 12.8k-unknown gravity
step and, with 1 and 2, on the benchmark); numpy's OpenBLAS reductions (vector
norms and dot products over 10,000 entries) did not, so until session 15 the default two
threads took another path than one (CC 383 iterations against 343 on the hemisphere).
The solver now runs OpenBLAS on one thread (``serial_openblas``), so the path, and every
figure but the times, is the same whatever ``MKL_NUM_THREADS``; the element kernel's
threads (``[mechanics.solver] assembly_threads``, :mod:`regtrack.mechanics.parallel`)
keep every sum in the serial order, so they do not change it either.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from regtrack.mechanics.config import MechanicsConfig
from regtrack.mechanics.meshes import hemisphere_model
from regtrack.mechanics.protocol import shipped_protocol
from regtrack.mechanics.run_view import (run_protocol_on_model, summarise,
                                         write_outputs)


def reference_iteration(model, repeats: int = 5) -> float:
    """Wall seconds of one average Newton iteration's work on ``model`` at rest (median of
    ``repeats``): the tissue and skin evaluation with the tangent and without it (a line
    search), the system matrix, a third of a factorisation and eight re-used GMRES
    iterations (PARDISO solve + product), the proportions of the benchmark's CC with
    session 38's defaults (165 iterations, 54 factorisations, 1,329 GMRES iterations; kept
    as the yardstick when the defaults change).  The host's speed drifts by
    10-25 % between runs here; a protocol's time in these units (printed as "ref. it.")
    does not, so runs made at different times compare."""
    import numpy as np

    from regtrack.mechanics import problem as P
    from regtrack.mechanics.linsolve import LinearSolver
    from regtrack.mechanics.problem import constraint_positions

    pr = P.build_problem(model, MechanicsConfig())
    o = pr.config.solver
    zero, diag = constraint_positions(pr, pr.fixed_dofs)
    u = np.zeros_like(pr.X)
    ls = LinearSolver(o.linear_solver, reuse_factorisation=False, dof_nodes=P.dof_nodes(pr),
                      decoupled=pr.fixed_dofs)

    def system():
        A = P.system_matrix(pr, P.evaluate(pr, u))
        A.data[zero] = 0.0
        A.data[diag] = 1.0
        return A

    A = system()
    b = np.ones(A.shape[0])
    ls.solve(A, b)  # analysis, JIT and MKL warm-up
    be = ls.backend
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        P.evaluate(pr, u, want_k=False)
        A = system()
        t_asm = time.perf_counter() - t
        t = time.perf_counter()
        ls.solve(A, b)
        t_fac = time.perf_counter() - t
        t = time.perf_counter()
        for _ in range(8):
            A @ be.solve(b)
        times.append(t_asm + t_fac / 3 + time.perf_counter() - t)
    ls.release()
    return float(np.median(times))


def _run_view(model, view: str, out) -> tuple[str, float, float]:
    """One view's protocol; returns (its printed table, total wall s, process CPU s)."""
    c0 = time.process_time()
    res, timing = run_protocol_on_model(model, shipped_protocol(view), mechanics=MechanicsConfig())
    cpu = time.process_time() - c0
    hdr = (f"{'view':5} {'step':22} {'incr':>4} {'iter':>4} {'aug':>3} {'ls':>4} {'asm s':>7} "
           f"{'solve s':>7} {'total s':>7}")
    lines = [hdr]
    for st in res.steps:
        s = st.solver
        lines.append(f"{view:5} {st.name:22} {s.get('increments', 0):4d} "
                     f"{s.get('iterations', 0):4d} "
                     f"{s.get('augmentations', 0):3d} {s.get('line_search_trials', 0):4d} "
                     f"{s.get('t_assembly', 0):7.2f} "
                     f"{s.get('t_solve', 0):7.2f} {s.get('t_total', 0):7.2f}")
    sm = summarise(res, timing)
    tot = timing["total_s"]
    solve = sum(st.solver.get("t_solve", 0) for st in res.steps)
    lines.append(f"{view}: D = {100 * sm['D']:.1f} %, upper force {sm['upper_force_N']:.2f} N, "
                 f"penetration {sm['max_penetration_mm']:.4f} mm, {sm['iterations']} iterations, "
                 f"total {tot:.1f} s "
                 f"(setup {timing['setup_s']:.1f} s; linear solves {100 * solve / tot:.0f} %); "
                 f"CPU {cpu:.1f} s\n")
    if out:
        write_outputs(res, model, out, stem=f"bench_{view}")
    return "\n".join(lines), tot, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lc", type=float, default=3.0, help="mesh size (mm); 3.0 gives ~10k nodes")
    ap.add_argument("--views", nargs="+", default=["cc", "mlo"])
    ap.add_argument("--out", type=Path, default=None, help="also write the result files here")
    ap.add_argument("--model", type=Path, default=None, help="a model .vtu (regtrack mesh) "
                    "instead of the hemisphere")
    ap.add_argument("--concurrent", action="store_true", help="run the views at the same time, "
                    "one process each, as `regtrack run` does on two or more cores")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    t = time.perf_counter()
    if args.model:
        from regtrack.model.io import load_model
        model = load_model(args.model)
    else:
        model = hemisphere_model(50.0, args.lc, tumour_radius=8.0)
    t_mesh = time.perf_counter() - t
    print(f"model: {model.n_nodes} nodes, {model.n_tets} tets (meshing/loading {t_mesh:.1f} s)")
    ref0 = reference_iteration(model)
    t0 = time.perf_counter()
    if args.concurrent and len(args.views) > 1:
        import concurrent.futures as cf
        import multiprocessing

        spawn = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(len(args.views), mp_context=spawn) as pool:
            runs = list(pool.map(_run_view, [model] * len(args.views), args.views,
                                 [args.out] * len(args.views)))
    else:
        runs = [_run_view(model, view, args.out) for view in args.views]
    wall = time.perf_counter() - t0
    for text, _, _ in runs:
        print(text)
    how = "at the same time" if args.concurrent and len(args.views) > 1 else "one after the other"
    ref = 0.5 * (ref0 + reference_iteration(model))  # the host's speed before and after
    print(f"all views ({how}): {wall:.1f} s wall (sum of the protocols "
          f"{sum(r[1] for r in runs):.1f} s), {sum(r[2] for r in runs):.1f} s CPU")
    print(f"reference iteration {1e3 * ref0:.0f} ms before, {2e3 * ref - 1e3 * ref0:.0f} ms after "
          f"the runs: " + ", ".join(f"{v} {r[1] / ref:.0f}" for v, r in zip(args.views, runs))
          + f", all views {wall / ref:.0f} ref. it. (the targets: 60 s and 120 s are "
          f"{60 / ref:.0f} and {120 / ref:.0f} at this speed)")


if __name__ == "__main__":
    main()
