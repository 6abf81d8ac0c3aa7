"""The threaded element kernel gives the serial loop's results bit for bit.

The frictional protocols are chaotic in the last digit (README, "Status"), so the
threaded assembly (:mod:`regtrack.mechanics.parallel`) must not change any sum's order:
these tests compare with exact equality, no tolerance.
"""

from __future__ import annotations

import numpy as np

from regtrack.mechanics import parallel
from regtrack.mechanics import problem as P
from regtrack.mechanics import tissue
from regtrack.mechanics.config import MechanicsConfig, SolverOptions
from regtrack.mechanics.meshes import box_model


def _problem(threads: int, formulation: str = "p1-anp") -> P.Problem:
    # 12 x 10 x 9 cubes of 6 tetrahedra: 6,480 elements, enough for three threads
    m = box_model((24.0, 20.0, 18.0), (12, 10, 9))
    m.fixed = m.points[:, 0] < 1e-9
    cfg = MechanicsConfig(formulation=formulation, solver=SolverOptions(assembly_threads=threads))
    return P.build_problem(m, cfg)


def _state(pr: P.Problem) -> np.ndarray:
    rng = np.random.default_rng(7)
    x = pr.X
    # a smooth large deformation (stretch, shear, twist) plus small noise: no inversion
    u = np.stack([0.2 * x[:, 0] + 0.1 * x[:, 2], -0.15 * x[:, 1] + 0.02 * x[:, 0] * x[:, 2] / 18.0,
                  0.05 * np.sin(x[:, 0] / 5.0) * x[:, 2]], axis=1)
    return u + 0.01 * rng.standard_normal(u.shape)


def _same(a: P.Evaluation, b: P.Evaluation) -> None:
    np.testing.assert_array_equal(a.f, b.f)
    np.testing.assert_array_equal(a.data, b.data)
    assert a.energy == b.energy
    assert a.n_inverted == b.n_inverted == 0
    if a.dv is not None:
        np.testing.assert_array_equal(a.dv, b.dv)


def test_thread_counts_give_identical_forces_tangents_and_energy():
    serial = _problem(1)
    assert len(serial.parts) == 1 and serial.parts[0].owned.all()
    u = _state(serial)
    ref = P.evaluate(serial, u)
    A_ref = P.system_matrix(serial, ref)
    for threads in (2, 3):
        pr = _problem(threads)
        assert len(pr.parts) == threads
        # every node owned by exactly one part; every element of a part touches it
        owners = np.sum([p.owned for p in pr.parts], axis=0)
        assert np.all(owners == 1)
        for p in pr.parts:
            assert np.all(p.owned[pr.tets[p.elems]].any(axis=1))
            assert np.all(np.diff(p.elems) > 0)
        ev = P.evaluate(pr, u)
        _same(ref, ev)
        np.testing.assert_array_equal(P.system_matrix(pr, ev).data, A_ref.data)
        np.testing.assert_array_equal(P.evaluate(pr, u, want_k=False).f, ref.f)


def test_plain_p1_and_an_arbitrary_partition_are_identical_too():
    """Any split of the nodes (here a random, scattered one into 4 parts) gives the same
    bits: the order of summation depends on the element numbering only."""
    pr = _problem(1, "p1")
    u = _state(pr)
    ref = P.evaluate(pr, u)
    owner = np.random.default_rng(3).integers(0, 4, pr.n_nodes)
    pr.parts = [parallel.Part(owner == t, np.flatnonzero((owner == t)[pr.tets].any(axis=1)))
                for t in range(4)]
    _same(ref, P.evaluate(pr, u))


def test_inverted_elements_are_counted_once_and_small_meshes_stay_serial():
    pr = _problem(3)
    u = _state(pr)
    e = 1234
    a, rest = pr.tets[e, 0], pr.tets[e, 1:]
    xa = pr.X[a] + u[a]
    c = (pr.X[rest] + u[rest]).mean(axis=0)
    u[a] = 2.0 * c - xa - pr.X[a]  # node a reflected through its opposite face: J < 0
    ev = P.evaluate(pr, u)
    serial = _problem(1)
    assert ev.n_inverted == P.evaluate(serial, u).n_inverted >= 1
    assert not np.isfinite(ev.energy)
    # the kernel itself counts each inverted element once, in the part of its first node
    x = pr.X + u
    counts, energies = [], []
    for prob in (serial, pr):
        ne = len(prob.tets)
        f, dv, ee = np.zeros((prob.n_nodes, 3)), np.zeros((ne, 4, 3)), np.full(ne, np.nan)
        args = (x, prob.tets, prob.G, prob.V, prob.mats.c1, np.zeros(ne), np.zeros(ne), False, False, f,
                np.zeros(1), prob.tet_base, prob.pattern.rowstride, dv, ee)
        counts.append(sum(parallel.run_parts(tissue.tet_kernel, args, prob.parts)))
        energies.append(ee)
    assert counts[0] == counts[1] == ev.n_inverted
    np.testing.assert_array_equal(energies[0], energies[1])  # no NaN left: every element set
    small = box_model((2.0, 2.0, 2.0), (3, 3, 3))  # 162 elements
    assert len(parallel.node_partition(len(small.points), small.tets, 4)) == 1
    assert parallel.thread_count(3) == 3 and 1 <= parallel.thread_count(0) <= parallel.MAX_AUTO_THREADS


def test_auto_thread_count_follows_the_study_workers_share(monkeypatch):
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    assert parallel.thread_count(0) == 1
    assert parallel.thread_count(2) == 2  # an explicit count wins
    monkeypatch.delenv("NUMBA_NUM_THREADS")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert parallel.thread_count(0) == 1


def test_a_failing_part_raises_in_the_caller():
    parts = parallel.node_partition(10, np.zeros((0, 4), np.int64), 1) * 3

    def boom(x, elems, owned):
        raise ValueError(f"bad {x}")

    try:
        parallel.run_parts(boom, (5,), parts)
    except ValueError as exc:
        assert "bad 5" in str(exc)
    else:
        raise AssertionError("run_parts swallowed the error")
