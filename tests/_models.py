"""Coarse patient models of the bundled sample cases, built once per test process.

Several slow tests simulate on the same coarse model of a sample case (the case's own
``[model]`` settings with ``target_nodes = 1500``: ``phantom01`` ~1.8k nodes,
``pelicano_exam03`` ~1.6k nodes).  Meshing one takes 10 to 20 s on 2 cores, and the mesher
is deterministic (gmsh, single-threaded Delaunay), so a model built once serves every test
that asks for the same case and size: :func:`coarse_model` keeps it for the rest of the
pytest process.

The model is shared, not copied: a test must not change it in place (simulations take it
read-only; a test that needs another set-up makes its own copy).  Tests in a child process
(``test_minimise``'s thread test) get it through :func:`save_coarse_model`, a pickle in
the test's temporary folder.

Imported as ``tests._models`` everywhere, so that there is one cache per process.
"""

from __future__ import annotations

import dataclasses
import functools
import pickle
from pathlib import Path

from regtrack.model.types import BreastModel

SAMPLE_CASES = Path(__file__).resolve().parents[1] / "sample_cases"


@functools.lru_cache(maxsize=None)
def _build(case_dir: str, target_nodes: int) -> BreastModel:
    from regtrack.case import load_case
    from regtrack.imaging.readers import read_label_map
    from regtrack.model.build import build_model

    case = load_case(case_dir, deep=False)
    cfg = dataclasses.replace(case.config("model"), target_nodes=target_nodes)
    return build_model(read_label_map(case.mri.labels), scheme=case.mri.scheme, config=cfg,
                       side=case.mri.side)


def coarse_model(case: str | Path, target_nodes: int = 1500) -> BreastModel:
    """The model of a sample case (a name under ``sample_cases/`` or a folder) meshed with
    the case's ``[model]`` settings and ``target_nodes``; built on the first call."""
    case_dir = Path(case) if Path(case).is_absolute() else SAMPLE_CASES / case
    return _build(str(case_dir.resolve()), int(target_nodes))


def save_coarse_model(path: str | Path, case: str | Path, target_nodes: int = 1500) -> Path:
    """Pickle :func:`coarse_model` to ``path`` for a child process; return ``path``."""
    path = Path(path)
    path.write_bytes(pickle.dumps(coarse_model(case, target_nodes)))
    return path
