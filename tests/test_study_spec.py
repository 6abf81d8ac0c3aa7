"""Study TOML validation, grid expansion and the parameter -> override mapping."""

from __future__ import annotations

import pytest

from regtrack.errors import ConfigError
from regtrack.study.params import apply_point
from regtrack.study.runner import make_runs
from regtrack.study.spec import load_study
from tests._study_fakes import make_case


def _write(tmp_path, body: str, cases=("A", "B")):
    for c in cases:
        make_case(tmp_path / "cases", c)
    p = tmp_path / "s.toml"
    p.write_text(body)
    return p


BASE = '[study]\nrunner = "fake"\n[cases]\nglob = "cases/*"\n'


def test_grid_expansion_and_order(tmp_path):
    p = _write(tmp_path, BASE + '[parameters]\nc1 = {start = 0.25, stop = 4.0, num = 5, scale = "log"}\n'
               'nu = {start = 0.45, stop = 0.49, step = 0.01}\nfriction = 0.2\n')
    st = load_study(p)
    # log grid: ratio 2 exactly; values rounded to 10 significant digits (stable cache keys)
    assert st.parameters["c1"] == (0.25, 0.5, 1.0, 2.0, 4.0)
    assert st.parameters["nu"] == (0.45, 0.46, 0.47, 0.48, 0.49)
    assert st.parameters["friction"] == (0.2,)
    pts = st.points()
    assert len(pts) == 25 and pts[0] == {"c1": 0.25, "nu": 0.45, "friction": 0.2}
    assert pts[1]["nu"] == 0.46  # last parameter varies fastest
    runs = make_runs(st)
    assert len(runs) == 50 == st.n_runs
    assert [r.case_id for r in runs[:25]] == ["A"] * 25
    assert len({r.run_key for r in runs}) == 50
    assert not (tmp_path / "s_results").exists()  # loading and expanding write nothing


def test_zip_combination(tmp_path):
    p = _write(tmp_path, BASE.replace('[study]\n', '[study]\ncombine = "zip"\n')
               + "[parameters]\nc1 = [0.5, 1.0]\nnu = [0.45, 0.49]\n")
    assert load_study(p).points() == [{"c1": 0.5, "nu": 0.45}, {"c1": 1.0, "nu": 0.49}]


def test_override_mapping():
    base = {"model": {"target_nodes": 2000}}
    ov = apply_point(base, {"c1": 0.8, "nu": 0.47, "tumour_ratio": 10.0, "friction": 0.3,
                            "target_D": 0.4, "mesh_nodes": 3000,
                            "registration.bracket_deg": 20.0}, views=("CC", "MLO"))
    assert ov == {"model": {"target_nodes": 3000},
                  "mechanics": {"tissue_c1_kpa": 0.8, "nu": 0.47, "tumour_c1_kpa": 8.0,
                                "tissue_model": "homogeneous"},
                  "contact": {"friction": 0.3},
                  "protocol": {"CC": {"target_D": 0.4}, "MLO": {"target_D": 0.4}},
                  "registration": {"bracket_deg": 20.0}}
    assert base == {"model": {"target_nodes": 2000}}  # not mutated
    # a study that names the tissue model keeps it; one without c1 leaves the case's
    assert apply_point({"mechanics": {"tissue_model": "composition"}}, {"c1": 0.8}, views=("CC",)) \
        == {"mechanics": {"tissue_model": "composition", "tissue_c1_kpa": 0.8}}
    assert apply_point({}, {"nu": 0.45}, views=("CC",)) == {"mechanics": {"nu": 0.45}}


def test_run_key_depends_on_case_content(tmp_path):
    p = _write(tmp_path, BASE + "[parameters]\nc1 = [0.5]\n")
    k1 = [r.run_key for r in make_runs(load_study(p))]
    (tmp_path / "cases" / "B" / "labels.txt").write_text("edited")
    k2 = [r.run_key for r in make_runs(load_study(p))]
    assert k1[0] == k2[0] and k1[1] != k2[1]


@pytest.mark.parametrize("body, match", [
    ("[parameters]\nnu = [0.45, 0.5]\n", r"\[parameters\] nu = 0.5: must be < 0.5"),
    ("[parameters]\nc1 = [-1.0]\n", r"\[parameters\] c1 = -1.0 kPa: must be > 0"),
    ("[parameters]\nc1 = {start = 1, stop = 2}\n", r"c1 = .*give exactly one of num or step"),
    ("[parameters]\nc1 = {start = 0, stop = 2, num = 3, scale = 'log'}\n", "log grid needs start"),
    ("[parameters]\nc1 = [1.0, 1.0]\n", "duplicate values"),
    ("[parameters]\nstiffness = [1.0]\n", r"stiffness: unknown parameter"),
    ("[parameters]\ntumour_ratio = [5.0]\n", "tumour_ratio: needs the tissue c1"),
    ("[parameters]\nmesh_nodes = [2.5]\n", "mesh_nodes = 2.5: expected int"),
    ("[parameterz]\n", r"unknown section \[parameterz\] \(did you mean \[parameters\]\?\)"),
])
def test_bad_study_files_name_file_and_key(tmp_path, body, match):
    p = _write(tmp_path, BASE + body)
    with pytest.raises(ConfigError, match=match) as err:
        load_study(p)
    assert str(p) in str(err.value)
    assert not (tmp_path / "s_results").exists()


def test_bad_study_section_values(tmp_path):
    p = _write(tmp_path, '[study]\nviews = ["CC", "AP"]\noutputs = ["csv", "xls"]\nworkers = -1\n'
               'runner = "nocolon"\n[cases]\npaths = ["cases/A", "missing"]\n')
    with pytest.raises(ConfigError) as err:
        load_study(p)
    msg = str(err.value)
    for part in ("views = ['CC', 'AP']", "unknown 'xls'", "workers = -1",
                 "runner = 'nocolon': unknown runner; known runners: ",
                 "'missing' is not a case folder"):
        assert part in msg
    assert msg.startswith("5 problems")


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="study file not found"):
        load_study(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[study\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_study(bad)


def test_empty_glob_and_duplicate_ids(tmp_path):
    p = _write(tmp_path, BASE.replace("cases/*", "nothing/*"))
    with pytest.raises(ConfigError, match=r"glob = 'nothing/\*': matches no case folder"):
        load_study(p)
    make_case(tmp_path / "other", "A")
    p.write_text(BASE.replace('glob = "cases/*"', 'paths = ["cases/A", "other/A"]'))
    with pytest.raises(ConfigError, match="case id 'A' used by both"):
        load_study(p)


@pytest.mark.parametrize("runner, message", [
    # issue 53: 'runner = "this:s"' imported the module and printed the Zen of Python
    ("this:s", r"runner = 'this:s': unknown runner; import paths are no longer accepted, name a "
               r"registered runner; known runners: bad_rows, fake, pipeline"),
    ("os:system", r"runner = 'os:system': unknown runner; import paths are no longer accepted"),
    ("pipline",
     r"runner = 'pipline': unknown runner \(did you mean 'pipeline'\?\); known runners: "),
])
def test_a_study_file_names_a_runner_never_code(tmp_path, runner, message):
    """A study TOML may only name a registered runner; an import path is refused before any
    module is imported (no run, nothing written)."""
    import sys

    sys.modules.pop("this", None)
    p = _write(tmp_path, BASE.replace('"fake"', f'"{runner}"'))
    with pytest.raises(ConfigError, match=message) as err:
        load_study(p)
    assert "\n" not in str(err.value) and "this" not in sys.modules
    assert not (tmp_path / "s_results").exists()


def test_runner_registry_resolves_names_only():
    from regtrack.study.runner import known_runners, pipeline_runner, resolve_runner
    from tests._study_fakes import fake_runner

    assert {"pipeline", "fake", "bad_rows"} <= set(known_runners())
    assert resolve_runner("pipeline") is pipeline_runner
    assert resolve_runner("fake") is fake_runner
    with pytest.raises(ConfigError, match=r"runner = 'tests\._study_fakes:fake_runner': unknown"):
        resolve_runner("tests._study_fakes:fake_runner")


def test_the_pipeline_runner_is_declared_as_an_entry_point():
    """pyproject.toml declares the built-in runner in the group other packages extend."""
    import tomllib
    from pathlib import Path

    from regtrack.study.runner import ENTRY_POINT_GROUP

    doc = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    eps = doc["project"]["entry-points"][ENTRY_POINT_GROUP]
    assert eps["pipeline"] == "regtrack.study.runner:pipeline_runner"


def test_installed_packages_add_runners_through_entry_points(monkeypatch):
    """A runner declared by another package (entry point group 'regtrack.study_runners')
    is known by its name and loaded on use; one whose module is gone is a ConfigError."""
    from importlib.metadata import EntryPoint

    from regtrack.study import runner as R
    from tests._study_fakes import fake_runner

    eps = {"ext": EntryPoint("ext", "tests._study_fakes:fake_runner", R.ENTRY_POINT_GROUP),
           "gone": EntryPoint("gone", "no_such_module_xyz:run", R.ENTRY_POINT_GROUP)}
    monkeypatch.setattr(R, "_entry_points", lambda: eps)
    assert {"ext", "gone", "pipeline"} <= set(R.known_runners())
    assert R.resolve_runner("ext") is fake_runner
    with pytest.raises(ConfigError, match=r"runner = 'gone': its entry point 'no_such_module_xyz:"
                                          r"run' \(group regtrack\.study_runners\) cannot be "
                                          r"loaded \(No module named 'no_such_module_xyz'\)"):
        R.resolve_runner("gone")
