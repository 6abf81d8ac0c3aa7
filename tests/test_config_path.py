"""One path for a setting: ``tissue_c1_kpa`` from case.toml, ``--set`` or a study.

The tissue's c1 can be given three ways: ``[mechanics] tissue_c1_kpa`` in case.toml,
``regtrack run --set mechanics.tissue_c1_kpa=...`` and a study's ``c1`` parameter.  All
three go through :func:`regtrack.case.resolve_configs` and must reach the element
kernel's input (the :class:`~regtrack.mechanics.problem.Problem`'s ``mats.c1``, MPa, as
the simulate stage builds it) and the run's provenance (the report's configuration
table) bit for bit the same, with the same simulation cache key.
"""

from __future__ import annotations

import numpy as np
import pytest

from regtrack.case import load_case, resolve_configs
from regtrack.cli.run import parse_sets
from regtrack.pipeline import stages
from regtrack.pipeline.run import open_run, provenance
from regtrack.study.params import apply_point
from tests.test_case import build_case, valid_doc, write_doc

C1_KPA = 0.83


class _Stop(Exception):
    """Raised by the patched solver factory once the Problem is built."""


@pytest.fixture(scope="module")
def model():
    from regtrack.mechanics.meshes import hemisphere_model

    return hemisphere_model(30.0, 8.0, tumour_radius=6.0)


def _case(root, *, c1_in_toml: bool):
    build_case(root)
    doc = valid_doc()
    doc["mechanics"] = {"tissue_c1_kpa": C1_KPA} if c1_in_toml else {}
    if not doc["mechanics"]:
        del doc["mechanics"]
    write_doc(root, doc)
    return load_case(root)


def _kernel_input_and_provenance(tmp_path, monkeypatch, model, case, overrides):
    """``mats.c1`` of the Problem the simulate stage builds, the provenance, the key."""
    import regtrack.mechanics.minimise as minimise

    seen = {}

    def capture(problem, **kw):
        seen["c1"] = problem.mats.c1.copy()
        raise _Stop

    monkeypatch.setattr(minimise, "minimiser_from_problem", capture)
    ctx = open_run(case, resolve_configs(case, overrides), cache_dir=tmp_path / "cache")
    mesh = stages.MeshOutput("mesh-key", tmp_path, model)
    with pytest.raises(_Stop):
        stages.simulate_stage(ctx, mesh, "CC")
    return seen["c1"], provenance(ctx, mesh, []), stages.simulate_key(ctx, mesh.key, "CC")


def test_c1_from_case_toml_set_and_study_reaches_the_kernel_identically(tmp_path, monkeypatch,
                                                                        model):
    in_toml = _case(tmp_path / "a", c1_in_toml=True)
    plain = _case(tmp_path / "b", c1_in_toml=False)
    ways = {
        "case.toml": (in_toml, None),
        "--set": (plain, parse_sets([f"mechanics.tissue_c1_kpa={C1_KPA}"])),
        "study": (plain, apply_point({}, {"c1": C1_KPA}, views=("CC",))),
    }
    got = {name: _kernel_input_and_provenance(tmp_path / name, monkeypatch, model, case, ov)
           for name, (case, ov) in ways.items()}
    c1_ref, prov_ref, key_ref = got["case.toml"]
    tissue = model.region == 1
    assert tissue.any() and (~tissue).any()
    # kPa in the case, MPa in the kernel: the one conversion (1e-3) is exact for this value
    assert np.array_equal(c1_ref[tissue], np.full(tissue.sum(), C1_KPA * 1e-3))
    assert not np.allclose(c1_ref[~tissue], C1_KPA * 1e-3)   # the tumour keeps its own c1
    for name, (c1, prov, key) in got.items():
        assert np.array_equal(c1, c1_ref), name
        assert prov["config"]["mechanics"]["tissue_c1_kpa"] == C1_KPA, name
        assert prov["config"] == prov_ref["config"], name
        assert key == key_ref, name   # same inputs, same cached simulation


def test_a_different_c1_changes_the_kernel_input_and_the_cache_key(tmp_path, monkeypatch, model):
    plain = _case(tmp_path / "b", c1_in_toml=False)
    a = _kernel_input_and_provenance(tmp_path / "x", monkeypatch, model, plain,
                                     {"mechanics": {"tissue_c1_kpa": C1_KPA}})
    b = _kernel_input_and_provenance(tmp_path / "y", monkeypatch, model, plain,
                                     {"mechanics": {"tissue_c1_kpa": 2 * C1_KPA}})
    assert not np.array_equal(a[0], b[0])
    assert a[2] != b[2]


def test_overrides_layer_on_the_case_values(tmp_path):
    case = _case(tmp_path / "a", c1_in_toml=True)
    cfg = resolve_configs(case, {"mechanics": {"nu": 0.45}, "protocol": {"MLO": {"target_D": 0.25}}})
    assert cfg.mechanics.tissue_c1_kpa == C1_KPA and cfg.mechanics.nu == 0.45
    assert cfg.mechanics is not case.config("mechanics")
    assert resolve_configs(case).mechanics is case.config("mechanics")   # parsed once, by the loader
    assert cfg.protocol_tables["MLO"] == {"target_D": 0.25}
    steps = cfg.protocols["MLO"].to_dict()["steps"]
    assert steps[-1]["target_D"] == 0.25


def test_case_toml_protocol_table_reaches_the_protocol(tmp_path):
    """A ``[protocol.CC]`` of case.toml is the run's protocol (it was dropped before)."""
    build_case(tmp_path / "a")
    doc = valid_doc()
    doc["protocol"] = {"CC": {"target_D": 0.3}}
    write_doc(tmp_path / "a", doc)
    cfg = resolve_configs(load_case(tmp_path / "a"))
    assert cfg.protocols["CC"].to_dict()["steps"][-1]["target_D"] == 0.3
    assert cfg.protocols["MLO"].to_dict()["steps"][-1]["target_D"] == 0.28   # shipped


@pytest.mark.parametrize("overrides, match", [
    ({"mechanix": {"nu": 0.4}}, r"unknown section 'mechanix' \(did you mean 'mechanics'\?\)"),
    ({"mechanics": {"tisue_c1_kpa": 1.0}}, r"\[mechanics\]: unknown key 'tisue_c1_kpa'"),
    ({"mechanics": {"tissue_c1_kpa": -1.0}}, r"\[mechanics\] tissue_c1_kpa = -1.0 kPa: must be > 0"),
    ({"protocol": {"AP": {"target_D": 0.3}}}, r"\[protocol\.AP\]: unknown view 'AP'"),
])
def test_bad_overrides_name_the_setting(tmp_path, overrides, match):
    from regtrack.errors import CaseError

    case = _case(tmp_path / "a", c1_in_toml=False)
    with pytest.raises(CaseError, match=match):
        resolve_configs(case, overrides)
