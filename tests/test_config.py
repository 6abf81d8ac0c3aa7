from __future__ import annotations

from dataclasses import dataclass

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
