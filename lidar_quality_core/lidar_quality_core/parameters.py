"""Parameters declared once: in the metadata of a settings dataclass's fields (no rclpy).

A field made with :func:`param` carries its parameter's description, default, range,
choices and whether the node applies changes at run time. Everything else reads it from
there: the node's ROS declarations (``QualityNode.declare_settings``),
``process_bag``'s ``--param`` checks, the check of the shipped config YAML and each
package README's parameter table. A field made with :func:`group` holds a nested settings
dataclass whose parameters are flat parameters of the node (MIMO's merge settings).
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import MISSING, dataclass
from typing import Any, Callable, Mapping

__all__ = ["ParamSpec", "param", "group", "parameter_specs", "from_parameters", "check_value",
           "check_fields", "to_parameters", "validate"]

_KEY = "lq_param"
_GROUP = "lq_group"


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter. ``default`` is the parameter's value type and default (lists for
    sequences, as ROS has no tuples); ``to_field`` maps a parameter value to the field's
    (e.g. 0 -> None), ``to_param`` back."""

    name: str
    default: Any
    description: str
    min_value: float | None = None
    max_value: float | None = None
    open_min: bool = False              # the bounds themselves are outside the range
    open_max: bool = False
    choices: tuple | None = None
    live: bool = False                  # applied at run time (else read-only)
    to_field: Callable[[Any], Any] | None = None
    to_param: Callable[[Any], Any] | None = None

    def check(self, value) -> None:
        """Raise ``ValueError`` naming the parameter when ``value`` is not allowed."""
        check_value(self.name, value, min_value=self.min_value, max_value=self.max_value,
                    choices=self.choices, open_min=self.open_min, open_max=self.open_max)

    def field_value(self, value):
        value = tuple(value) if isinstance(value, list) else value
        return self.to_field(value) if self.to_field else value

    def param_value(self, value):
        value = self.to_param(value) if self.to_param else value
        return list(value) if isinstance(value, tuple) else value

    def range_text(self) -> str:
        """``Range [0, 1).``-style text, or ``""``."""
        if self.min_value is None and self.max_value is None:
            return ""
        lo = "-inf" if self.min_value is None else f"{self.min_value:g}"
        hi = "inf" if self.max_value is None else f"{self.max_value:g}"
        return (f"Range {'(' if self.open_min else '['}{lo}, {hi}"
                f"{')' if self.open_max else ']'}.")


def param(default, description: str, *, field_default=MISSING, **spec) -> dataclasses.Field:
    """A dataclass field that is a node parameter (keywords: see :class:`ParamSpec`).
    ``field_default`` when the field's default differs from the parameter's (``to_field``
    of the default otherwise)."""
    if not description:
        raise ValueError("a parameter needs a description")
    meta = {_KEY: dict(default=default, description=description, **spec)}
    if field_default is MISSING:
        field_default = tuple(default) if isinstance(default, list) else default
        if spec.get("to_field"):
            field_default = spec["to_field"](field_default)
    return dataclasses.field(default=field_default, metadata=meta)


def group(default) -> dataclasses.Field:
    """A field holding a settings dataclass whose parameters are the node's, flat."""
    return dataclasses.field(default=default, metadata={_GROUP: True})


def _fields(cls):
    return dataclasses.fields(cls if isinstance(cls, type) else type(cls))


def parameter_specs(cls) -> tuple[ParamSpec, ...]:
    """The parameters of settings class ``cls`` in field order (groups expanded in place)."""
    out = []
    for f in _fields(cls):
        if f.metadata.get(_GROUP):
            out.extend(parameter_specs(type(f.default)))
        elif _KEY in f.metadata:
            out.append(ParamSpec(name=f.name, **f.metadata[_KEY]))
    return tuple(out)


def from_parameters(cls, values: Mapping[str, Any], *, check: bool = True):
    """An instance of ``cls`` from parameter values by name (absent: the default); each
    value checked against its spec first. Fields that are not parameters keep their
    defaults (a group's non-parameter fields those of the group's default instance)."""
    kw = {}
    for f in _fields(cls):
        if f.metadata.get(_GROUP):
            sub = from_parameters(type(f.default), values, check=check)
            # keep the group default's non-parameter fields (e.g. MIMO's score_type)
            kw[f.name] = dataclasses.replace(
                f.default, **{g.name: getattr(sub, g.name) for g in _fields(sub)
                              if _KEY in g.metadata or g.metadata.get(_GROUP)})
        elif _KEY in f.metadata and f.name in values:
            spec = ParamSpec(name=f.name, **f.metadata[_KEY])
            if check:
                spec.check(values[f.name])
            kw[f.name] = spec.field_value(values[f.name])
    return cls(**kw)


def to_parameters(settings) -> dict:
    """``{parameter name: value}`` of a settings instance (groups flattened)."""
    out = {}
    for f in _fields(settings):
        v = getattr(settings, f.name)
        if f.metadata.get(_GROUP):
            out.update(to_parameters(v))
        elif _KEY in f.metadata:
            out[f.name] = ParamSpec(name=f.name, **f.metadata[_KEY]).param_value(v)
    return out


def validate(settings) -> None:
    """Run the ``validate()`` of ``settings`` and of every group in it that has one (the
    checks across parameters, e.g. an image too large, ``min_cluster_size`` > heads)."""
    for f in _fields(settings):
        if f.metadata.get(_GROUP):
            validate(getattr(settings, f.name))
    own = getattr(settings, "validate", None)
    if callable(own):
        own()


def check_fields(settings) -> None:
    """Check every parameter field of ``settings`` against its spec (``ValueError``)."""
    specs = {s.name: s for s in parameter_specs(settings)}
    for name, value in to_parameters(settings).items():
        specs[name].check(value)


def check_value(name: str, value: Any, *, min_value: float | None = None,
                max_value: float | None = None, choices: tuple | None = None,
                open_min: bool = False, open_max: bool = False) -> None:
    """Raise ``ValueError`` naming ``name`` when ``value`` is not finite, not one of
    ``choices`` or outside the range."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"parameter {name!r} = {value!r}: must be a finite number")
    if choices and value not in choices:
        raise ValueError(f"parameter {name!r} = {value!r}: expected one of {list(choices)}")
    if min_value is None and max_value is None:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"parameter {name!r} = {value!r}: expected a number")
    low = min_value is not None and (value <= min_value if open_min else value < min_value)
    high = max_value is not None and (value >= max_value if open_max else value > max_value)
    if low or high:
        lo = "-inf" if min_value is None else f"{min_value:g}"
        hi = "inf" if max_value is None else f"{max_value:g}"
        raise ValueError(f"parameter {name!r} = {value!r}: outside "
                         f"{'(' if open_min else '['}{lo}, {hi}{')' if open_max else ']'}")
