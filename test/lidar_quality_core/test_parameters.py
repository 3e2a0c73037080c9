"""Parameters declared once in settings dataclasses (lidar_quality_core.parameters)."""
from dataclasses import dataclass

import pytest

from lidar_quality_core.parameters import (check_fields, check_value, from_parameters, group,
                                           param, parameter_specs, to_parameters)


@dataclass(frozen=True)
class Inner:
    eps: float = param(0.5, "Radius.", min_value=0.0, max_value=1.0, open_min=True,
                       open_max=True)
    size: int | None = param(0, "Size; 0: automatic.", min_value=0,
                             to_field=lambda v: v or None, to_param=lambda v: v or 0)
    kind: str = "fixed"           # not a parameter: kept from the group's default


@dataclass(frozen=True)
class Middle:
    n: int = param(2, "Count.", min_value=1, max_value=16)
    inner: Inner = group(Inner(kind="chosen"))
    names: tuple = param(["a", "b"], "Names.")


@dataclass(frozen=True)
class Outer:
    settings: Middle = group(Middle())
    mode: str = param("x", "Mode.", choices=("x", "y"), live=True)


def test_specs_in_field_order_with_groups_flattened():
    specs = parameter_specs(Outer)
    assert [s.name for s in specs] == ["n", "eps", "size", "names", "mode"]
    by = {s.name: s for s in specs}
    assert by["names"].default == ["a", "b"] and by["mode"].live and not by["n"].live
    assert by["eps"].range_text() == "Range (0, 1)." and by["n"].range_text() == "Range [1, 16]."


def test_defaults_and_nested_values_reach_every_level():
    d = from_parameters(Outer, {})
    assert d == Outer() and d.settings.inner.kind == "chosen" and d.settings.names == ("a", "b")
    o = from_parameters(Outer, {"eps": 0.25, "size": 3, "n": 4, "names": ["c"], "mode": "y"})
    assert o.settings.inner == Inner(eps=0.25, size=3, kind="chosen")   # non-parameter kept
    assert o.settings.n == 4 and o.settings.names == ("c",) and o.mode == "y"
    assert from_parameters(Outer, {"size": 0}).settings.inner.size is None
    assert to_parameters(o) == {"n": 4, "eps": 0.25, "size": 3, "names": ["c"], "mode": "y"}
    assert to_parameters(Outer())["size"] == 0


@pytest.mark.parametrize("values, match", [
    ({"eps": 0.0}, r"'eps' = 0.0: outside \(0, 1\)"), ({"eps": 1.0}, r"outside \(0, 1\)"),
    ({"n": 17}, r"'n' = 17: outside \[1, 16\]"), ({"mode": "z"}, "expected one of"),
    ({"eps": float("nan")}, "finite"), ({"n": "3"}, "expected a number"),
    ({"n": True}, "expected a number")])
def test_values_checked_by_name(values, match):
    with pytest.raises(ValueError, match=match):
        from_parameters(Outer, values)


def test_check_fields_of_an_instance():
    check_fields(Outer())
    with pytest.raises(ValueError, match="'eps'"):
        check_fields(Outer(settings=Middle(inner=Inner(eps=1.5))))
    check_value("x", 5, min_value=0)              # closed bounds include the ends
    check_value("x", 0, min_value=0)
    with pytest.raises(ValueError):
        param(1, "")
