"""Thread-parallel element loops whose results do not depend on the thread count.

The Newton path of the frictional protocols is chaotic: a change in the last digit of one
force moves the iteration count of a compression step by tens of per cent (README,
"Status").  So the assembly is parallelised only in a way that keeps every floating-point
sum in the serial order:

* the mesh nodes are split into ``k`` parts (METIS, :func:`node_partition`);
* part ``t`` walks, in increasing element order, every element with a node in the part,
  and writes only the rows of the nodes it owns (forces, tangent rows, ``dv``).

Each row entry therefore receives its element contributions in the same order as in the
serial loop, and the results are bit-identical for any ``k`` (tested).  The price is that
an element on a part boundary has its kinematics computed by each part it touches.
The kernels are numba functions compiled with ``nogil=True`` and run in plain
``threading`` threads (no thread pool: nothing to go stale in a forked Dask worker).

Measured on the 9,496-node benchmark hemisphere (48,477 tetrahedra) at its compressed CC
state, this 2-core machine, alternated in one process: the kernel with the tangent takes
54-56 ms on 2 threads against 97-121 ms for the former serial kernel, 6.4-7.5 against
8.0-8.4 ms without it (``pipelines/bench_mechanics.py`` prints the one-thread assembly
beside the default).
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass

import numpy as np

#: Below this many elements a second thread is not worth starting (the serial kernel
#: takes about 1 ms per 1,000 tetrahedra with the tangent).
MIN_ELEMENTS_PER_THREAD = 2000
#: At most this many threads by default: two threads gave 1.8-2.1x on the two-core
#: machine this was measured on; with more parts the boundary elements computed twice grow.
MAX_AUTO_THREADS = 4


@dataclass(frozen=True)
class Part:
    """One thread's share: ``owned`` (N,) bool, the nodes whose rows it writes, and
    ``elems`` (increasing) the elements with at least one owned node."""

    owned: np.ndarray
    elems: np.ndarray


def thread_count(requested: int) -> int:
    """``requested`` if positive, else the CPUs this process may use, at most
    :data:`MAX_AUTO_THREADS` and at most ``NUMBA_NUM_THREADS`` / ``OMP_NUM_THREADS`` when
    set (the study workers set them to their share of the cores,
    :mod:`regtrack.study.backends`)."""
    if requested > 0:
        return int(requested)
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        n = os.cpu_count() or 1
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(var, "").strip()
        if value.isdigit() and int(value) > 0:
            n = min(n, int(value))
            break
    return max(1, min(n, MAX_AUTO_THREADS))


def node_partition(n_nodes: int, cells: np.ndarray, k: int) -> list[Part]:
    """Split the nodes of a mesh into ``k`` parts of about equal size (METIS on the node
    graph, pymetis's deterministic defaults) and list each part's elements.

    ``k <= 1`` (or too few elements) gives the single part that owns everything.
    """
    cells = np.asarray(cells)
    k = min(int(k), max(1, len(cells) // MIN_ELEMENTS_PER_THREAD))
    if k <= 1:
        return [Part(np.ones(n_nodes, bool), np.arange(len(cells), dtype=np.int64))]
    import pymetis

    from regtrack.mechanics.assembly import node_adjacency

    adj = node_adjacency(n_nodes, [cells])
    adj.setdiag(0)  # METIS takes no self-loops
    adj.eliminate_zeros()
    graph = pymetis.CSRAdjacency(adj.indptr.astype(np.int64), adj.indices.astype(np.int64))
    _, membership = pymetis.part_graph(k, adjacency=graph)
    membership = np.asarray(membership)
    parts = []
    for t in range(k):
        owned = membership == t
        parts.append(Part(owned, np.flatnonzero(owned[cells].any(axis=1)).astype(np.int64)))
    return parts


def run_parts(fn, args: tuple, parts: list[Part]) -> list:
    """``fn(*args, part.elems, part.owned)`` for every part, each in its own thread (the
    last in the calling thread); returns the results in part order.  ``fn`` must release
    the GIL (numba ``nogil=True``) for the threads to overlap."""
    results: list = [None] * len(parts)
    errors: list = []

    def work(i: int) -> None:
        try:
            results[i] = fn(*args, parts[i].elems, parts[i].owned)
        except BaseException as exc:  # re-raised in the caller below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,), daemon=True) for i in range(len(parts) - 1)]
    for th in threads:
        th.start()
    work(len(parts) - 1)
    for th in threads:
        th.join()
    if errors:
        raise errors[0]
    return results
