"""Foundation: package import, CLI start-up, atomic writes, volume affines, model I/O."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from regtrack import _io
from regtrack.imaging.volume import LabelVolume, make_affine
from regtrack.model.io import load_model, save_model
from regtrack.model.types import AnatomicalFrame, BreastModel


def test_cli_help_is_lazy():
    """`regtrack --help` must not import the heavy stack (numpy-level libs are fine)."""
    code = (
        "import sys; from regtrack.cli import build_parser; build_parser().format_help();"
        "heavy=[m for m in ('gmsh','scipy.sparse','pydicom','matplotlib','skfem','numba','dask') if m in sys.modules];"
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_cli_no_command_prints_help():
    r = subprocess.run([sys.executable, "-m", "regtrack.cli"], capture_output=True, text=True)
    assert r.returncode == 1 and "usage" in r.stdout.lower()


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with _io.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []
    _io.write_json(target, {"a": np.float64(1.5), "b": np.arange(3)})
    assert target.read_text().strip().startswith("{")
    with pytest.raises(ValueError):
        _io.write_json(tmp_path / "nan.json", {"x": float("nan")})
    assert not (tmp_path / "nan.json").exists()


def test_volume_affine_roundtrip():
    d = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)
    vol = LabelVolume(np.zeros((4, 5, 6), np.int16), make_affine([10, 20, 30], [0.5, 0.7, 2.0], d))
    np.testing.assert_allclose(vol.spacing, [0.5, 0.7, 2.0])
    ijk = np.array([[1.0, 2.0, 3.0], [0, 0, 0]])
    np.testing.assert_allclose(vol.world_to_index(vol.index_to_world(ijk)), ijk, atol=1e-12)
    # direction columns: axis 1 goes along +z (LPS), axis 2 along -y
    np.testing.assert_allclose(vol.index_to_world([0, 1, 0]) - vol.origin, [0, 0, 0.7])
    sub = vol.crop([1, 1, 1], [3, 3, 3])
    np.testing.assert_allclose(sub.origin, vol.index_to_world([1, 1, 1]))


def test_model_io_roundtrip(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    frame = AnatomicalFrame.standard("L", origin_lps=[1, 2, 3])
    m = BreastModel(pts, tets, [1, 2], [0, 1], [[1, 2, 4]], [1, 0, 0, 0, 0], 4, frame, meta={"k": 1})
    save_model(m, tmp_path / "m.vtu")
    m2 = load_model(tmp_path / "m.vtu")
    np.testing.assert_allclose(m2.points, pts)
    np.testing.assert_array_equal(m2.tets, tets)
    np.testing.assert_array_equal(m2.region, [1, 2])
    np.testing.assert_array_equal(m2.skin, [[1, 2, 4]])
    assert m2.nipple == 4 and m2.frame.side == "L" and m2.meta == {"k": 1}
    np.testing.assert_allclose(m2.frame.to_patient(m2.frame.to_model([5, 6, 7])), [5, 6, 7])


def test_run_set_overrides_parse_into_sections():
    from regtrack.cli.run import parse_sets
    from regtrack.errors import ConfigError

    assert parse_sets(["model.target_nodes=3000", "protocol.CC.target_D=0.3",
                       "contact.friction=0.2", "mechanics.skin_enabled=false"]) == {
        "model": {"target_nodes": 3000}, "protocol": {"CC": {"target_D": 0.3}},
        "contact": {"friction": 0.2}, "mechanics": {"skin_enabled": False}}
    for bad in ("target_nodes=3", "model.=3", "model.target_nodes"):
        with pytest.raises(ConfigError, match="SECTION.KEY=VALUE"):
            parse_sets([bad])


def test_run_set_checks_between_keys_see_every_setting():
    """Two --set items that are only valid together (formulation 'p2' has no skin membrane)
    pass, and the check between keys is made on the whole configuration (case.toml and
    every --set) before any work: one of them alone is an error naming the fix."""
    from pathlib import Path

    from regtrack.case import load_case, resolve_configs
    from regtrack.cli.run import parse_sets
    from regtrack.errors import CaseError

    case = load_case(Path(__file__).resolve().parents[1] / "sample_cases" / "phantom01", deep=False)
    both = parse_sets(["mechanics.skin_enabled=false", 'mechanics.formulation="p2"'])
    assert both == {"mechanics": {"skin_enabled": False, "formulation": "p2"}}
    cfg = resolve_configs(case, both)
    assert cfg.mechanics.formulation == "p2" and not cfg.mechanics.skin_enabled
    with pytest.raises(CaseError, match="skin_enabled = false"):
        resolve_configs(case, parse_sets(['mechanics.formulation="p2"']))
    # and a run refuses it before any stage: the mesh stage makes 4-node tetrahedra
    from regtrack.errors import ConfigError
    from regtrack.pipeline.run import open_run

    with pytest.raises(ConfigError, match="10-node tetrahedral model"):
        open_run(case, cfg)


def test_a_plate_edge_that_pinches_the_base_is_refused_before_any_work():
    """``--set protocol.CC.posterior_edge_mm=5`` (the rounded edge 5 mm in front of the chest
    wall) is refused by resolve_configs, naming case.toml's section and the fix; with the
    chest-wall contact off it is accepted (no wall to make a wedge with)."""
    from pathlib import Path

    from regtrack.case import load_case, resolve_configs
    from regtrack.cli.run import parse_sets
    from regtrack.errors import CaseError

    case = load_case(Path(__file__).resolve().parents[1] / "sample_cases" / "phantom01", deep=False)
    with pytest.raises(CaseError, match=r"case.toml \[protocol.CC\]: posterior_edge_mm = 5 .* 60 deg"):
        resolve_configs(case, parse_sets(["protocol.CC.posterior_edge_mm=5.0"]))
    cfg = resolve_configs(case, parse_sets(["protocol.CC.posterior_edge_mm=5.0",
                                            "contact.chest_wall_contact=false"]))
    assert cfg.protocols["CC"].plates.posterior_edge_mm == 5.0


def test_every_dependency_is_pinned_in_constraints():
    """make installs with constraints.txt: each direct dependency (core and test extra) of
    pyproject.toml must be pinned there (==), so a fresh clone cannot pick up an unpinned
    new release (a new MKL build moves the phantom's Newton path, see
    test_phantom_mammograms); and the pin must satisfy pyproject's own lower bound."""
    import re
    import tomllib
    from pathlib import Path

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    root = Path(__file__).resolve().parents[1]
    proj = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in proj["dependencies"] + proj["optional-dependencies"]["test"]]
    pins = {}
    for line in (root / "constraints.txt").read_text().splitlines():
        m = re.fullmatch(r"([A-Za-z0-9_.\-]+)==(\S+)", line.strip())
        if m:
            pins[canonicalize_name(m.group(1))] = m.group(2)
    missing = [r.name for r in reqs if canonicalize_name(r.name) not in pins]
    assert not missing, f"constraints.txt does not pin {missing}: run `make lock`"
    bad = [f"{r.name}=={pins[canonicalize_name(r.name)]} vs {r.specifier}" for r in reqs
           if not r.specifier.contains(pins[canonicalize_name(r.name)], prereleases=True)]
    assert not bad, f"pins outside pyproject's ranges: {bad}"
