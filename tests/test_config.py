from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest

from regtrack.config import param, parse_section


@dataclass(frozen=True)
class _Mat:
    c1_kpa: float = param(0.54, "kPa", "neo-Hookean c1", gt=0)
    nu: float = param(0.49, "-", "Poisson's ratio", ge=0.0, lt=0.5)
    kind: str = param("p1", choices=("p1", "p2"))
    steps: int = param(10, ge=1)


def test_parse_collects_all_problems_and_warns_unknown_keys():
    obj, problems, warnings = parse_section(
        _Mat, {"c1_kpa": -1, "nu": 0.5, "kind": "p3", "steps": "x", "nuu": 1}, where="case.toml [mechanics]"
    )
    assert len(problems) == 4
    assert any("c1_kpa = -1 kPa: must be > 0" in p for p in problems)
    assert any("nu = 0.5: must be < 0.5" in p for p in problems)
    assert any("kind = 'p3': must be one of 'p1', 'p2'" in p for p in problems)
    assert any("steps = 'x': expected int" in p for p in problems)
    assert warnings == ["case.toml [mechanics]: unknown key 'nuu' ignored (did you mean 'nu'?)"]
    assert obj.nu == 0.49  # defaults kept for bad keys


def test_parse_coerces_int_to_float():
    obj, problems, _ = parse_section(_Mat, {"c1_kpa": 2}, where="x")
    assert problems == [] and isinstance(obj.c1_kpa, float) and obj.c1_kpa == 2.0


def test_command_line_assignments_are_typed_and_validated():
    """``key=value`` overrides of the pipelines' ``--contact``: booleans, ints, floats and
    strings; a bad item, an unknown key or a value out of range is a ConfigError that
    names the option and the key."""
    from regtrack.config import config_from_assignments, parse_assignments
    from regtrack.errors import ConfigError
    from regtrack.mechanics.contact import ContactConfig

    assert parse_assignments(["friction=0.2", "chest_wall_contact=true", "max_augmentations=3",
                              "friction_bound=current"]) == {
        "friction": 0.2, "chest_wall_contact": True, "max_augmentations": 3,
        "friction_bound": "current"}
    c = config_from_assignments(ContactConfig, ["friction=0", "edge_band_mm=12.5"],
                                where="--contact")
    assert c.friction == 0.0 and c.edge_band_mm == 12.5
    for bad, words in ((["friction"], "not key=value"),
                       (["frction=0.1"], "did you mean 'friction'"),
                       (["friction=-1"], "friction"),
                       (["friction_bound=sometimes"], "friction_bound")):
        with pytest.raises(ConfigError, match=words) as err:
            config_from_assignments(ContactConfig, bad, where="--contact")
        assert "--contact" in str(err.value)



@dataclasses.dataclass(frozen=True)
class _Inner:
    a: int = param(1, "-", "", ge=0)
    b: int = param(2, "-", "", ge=0)


@dataclasses.dataclass(frozen=True)
class _Outer:
    x: float = param(0.5, "-", "", gt=0)
    y: float = param(0.25, "-", "", gt=0)
    inner: _Inner = dataclasses.field(default_factory=_Inner)


def test_parse_section_layers_a_table_on_a_base():
    """``base=``: the table's keys replace the base's values, nested sections merge, the
    other values (and a nested section's other keys) stay the base's."""
    base, p, _ = parse_section(_Outer, {"x": 2.0, "inner": {"a": 5}}, where="case [s]")
    assert not p and base == _Outer(2.0, 0.25, _Inner(5, 2))
    top, p, _ = parse_section(_Outer, {"y": 3.0, "inner": {"b": 7}}, where="--set [s]", base=base)
    assert not p and top == _Outer(2.0, 3.0, _Inner(5, 7))
    bad, p, _ = parse_section(_Outer, {"y": -1.0}, where="--set [s]", base=base)
    assert p == ["--set [s] y = -1.0: must be > 0"] and bad == base
