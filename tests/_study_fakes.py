"""Deterministic stand-ins for the pipeline, for testing the study engine.

Importing this module registers them as the study runners ``"fake"`` and ``"bad_rows"``
(:func:`regtrack.study.runner.register_runner`, the test-only alternative to the
``regtrack.study_runners`` entry points); the engine pickles the functions by reference,
which the worker processes (local pool and Dask) can import because the repository root is
on ``sys.path``.

:func:`fake_runner` behaves like ``regtrack.pipeline.run.run_case`` seen from outside:

* it uses the stage cache (``StageCache(spec.cache_dir)``) for a "mesh" keyed by the case
  and ``[model]`` overrides and a "simulation" per view keyed by everything but
  ``[registration]``, and logs every stage it actually *builds* under ``<cache>/fake-log``;
* it logs every call under ``<cache>/fake-calls/<run_key>.<unique>``;
* it returns one row per view whose metrics are smooth known functions of the
  parameters (peak of the score ``(BS_Av + TS_Av) / 2`` at c1 = 0.8 kPa, nu = 0.47);
* the case's ``case.toml`` may hold a ``[fake]`` table: ``fail = "mesh"`` raises
  :class:`MeshQualityError`; ``crash = "once"`` / ``"always"`` kills the worker process
  (``os._exit``) on the first / every attempt; ``sleep = s`` waits s seconds;
  ``seed`` shifts the metrics.
"""

from __future__ import annotations

import math
import os
import time
import tomllib
import uuid
from pathlib import Path

from regtrack.errors import MeshQualityError
from regtrack.pipeline.cache import StageCache, fingerprint
from regtrack.study.runner import register_runner

C1_STAR = 0.8  # kPa, where the fake score peaks
NU_STAR = 0.47


def _log(root: Path, sub: str, name: str) -> None:
    d = root / sub
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{name}.{uuid.uuid4().hex[:8]}").write_text("")


def calls(cache_dir: Path) -> list[str]:
    """Run keys of every call made to the fake runner (one entry per call)."""
    d = Path(cache_dir) / "fake-calls"
    return sorted(p.name.split(".")[0] for p in d.iterdir()) if d.is_dir() else []


def builds(cache_dir: Path, stage: str) -> list[str]:
    """Keys of every stage the fake runner built (not found in the stage cache)."""
    d = Path(cache_dir) / "fake-log"
    return sorted(p.name.split(".")[1] for p in d.glob(f"{stage}.*")) if d.is_dir() else []


def metrics(c1: float, nu: float, *, friction: float = 0.1, target_d: float | None = None,
            seed: float = 0.0) -> dict:
    """Known smooth metrics of the fake pipeline (percent, mm, N)."""
    u = math.log(c1 / C1_STAR)
    bs = 92.0 - 8.0 * u * u - 4e4 * (nu - NU_STAR) ** 2 - 5.0 * friction + seed
    ts = 80.0 - 12.0 * u * u - 6e4 * (nu - NU_STAR) ** 2 + seed
    d = target_d if target_d is not None else 0.45 - 0.1 * math.log(c1 / 0.54)
    return {"BS_Av": bs, "TS_Av": ts, "theta_p_b": 2.0 * u, "theta_p_t": 3.0 * u,
            "theta_p": 2.5 * u, "D": d, "d_T": 3.0 + 10.0 * abs(u) + 100 * abs(nu - NU_STAR),
            "d_B": 1.0 + abs(u), "force_N": 60.0 * c1 * (1 + 10 * (nu - 0.45))}


def fake_runner(spec) -> list[dict]:
    case = Path(spec.case_dir)
    doc = tomllib.loads((case / "case.toml").read_text())
    fake = doc.get("fake", {})
    cache_root = Path(spec.cache_dir)
    _log(cache_root, "fake-calls", spec.run_key)
    crash = fake.get("crash")
    marker = cache_root / "fake-crash" / spec.run_key
    if crash == "always" or (crash == "once" and not marker.exists()):
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text("crashed")
        os._exit(17)
    if fake.get("sleep"):
        time.sleep(float(fake["sleep"]))
    if fake.get("fail") == "mesh":
        raise MeshQualityError(f"{case / 'case.toml'}: mesh has 3 inverted tets after 3 retries; "
                               "coarsen [model] target_nodes")
    ov = spec.overrides
    cache = StageCache(cache_root / "stages")
    mesh_key = fingerprint("mesh", spec.case_id, ov.get("model", {}))
    if cache.lookup("mesh", mesh_key) is None:
        with cache.produce("mesh", mesh_key) as d:
            time.sleep(float(fake.get("mesh_s", 0.0)))
            (d / "mesh.txt").write_text("mesh")
        _log(cache_root, "fake-log", f"mesh.{mesh_key}")
    mech = ov.get("mechanics", {})
    c1 = float(mech.get("tissue_c1_kpa", 0.54))
    nu = float(mech.get("nu", 0.49))
    friction = float(ov.get("contact", {}).get("friction", 0.1))
    rows = []
    for view in spec.views:
        sim_key = fingerprint("sim", mesh_key, {k: v for k, v in ov.items()
                                                if k not in ("registration", "model")}, view)
        if cache.lookup("sim", sim_key) is None:
            with cache.produce("sim", sim_key) as d:
                (d / "sim.txt").write_text("sim")
            _log(cache_root, "fake-log", f"sim.{sim_key}")
        target = ov.get("protocol", {}).get(view, {}).get("target_D")
        m = metrics(c1, nu, friction=friction, target_d=target, seed=float(fake.get("seed", 0.0)))
        if view == "MLO":
            m = {k: v * 0.97 for k, v in m.items()}
        rows.append({"case_id": spec.case_id, "view": view, **m})
    return rows


def bad_rows_runner(spec) -> list[dict]:
    """Returns a row for the wrong view (an engine-side result check must catch it)."""
    return [{"case_id": spec.case_id, "view": "XX", "BS_Av": 1.0}]


register_runner("fake", fake_runner)
register_runner("bad_rows", bad_rows_runner)


def make_case(root: Path, name: str, **fake) -> Path:
    """A fake case folder ``root/name`` with ``case.toml`` (``[fake]`` table from kwargs)."""
    d = root / name
    d.mkdir(parents=True, exist_ok=True)
    lines = ["[case]", f'id = "{name}"', "", "[fake]"]
    for k, v in fake.items():
        lines.append(f"{k} = {v!r}" if not isinstance(v, str) else f'{k} = "{v}"')
    (d / "case.toml").write_text("\n".join(lines) + "\n")
    (d / "labels.txt").write_text(f"content of {name}\n")
    return d
