"""Parameter declaration with mandatory descriptions."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from lidar_quality_core.parameters import ParamSpec, check_value
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}


_LIVE = " Can be changed at run time (ros2 param set)."
_READ_ONLY = " Read at start-up (read-only: restart the node to change it)."
#: parameters rclpy declares on every node (not ours to document)
RCLPY_PARAMETERS = ("use_sim_time", "start_type_description_service")


def declare(node, name: str, default: Any, description: str, *, read_only: bool = True,
            min_value: float | None = None, max_value: float | None = None,
            choices: tuple[str, ...] | None = None, open_min: bool = False,
            open_max: bool = False) -> Any:
    """Declare ``name`` with a description (and range / choices) and return its value.

    Values outside the range or the choices, and non-finite floats, raise ``ValueError``
    naming the parameter, so a misconfigured node fails at start-up with a clear message.
    Parameters are read-only unless ``read_only=False``: the nodes read them once at
    start, and ``ros2 param set`` on one of them is refused ("read-only", restart the
    node with the new value) instead of being accepted and ignored. A node that applies
    a parameter at run time declares it with ``read_only=False`` and handles the change.
    ROS ranges are closed: an open bound (``open_min`` / ``open_max``) is stated in the
    descriptor's additional constraints and enforced here.
    """
    if not description:
        raise ValueError(f"parameter {name!r} needs a description")
    description += _LIVE if not read_only else _READ_ONLY
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only,
                               type=_TYPES.get(type(default), ParameterType.PARAMETER_NOT_SET))
    if choices:
        desc.additional_constraints = "one of: " + ", ".join(choices)
    if open_min or open_max:
        desc.additional_constraints = ParamSpec(name, default, description, min_value, max_value,
                                                open_min, open_max).range_text()
    if min_value is not None or max_value is not None:
        lo = -float("inf") if min_value is None else min_value
        hi = float("inf") if max_value is None else max_value
        if isinstance(default, int) and not isinstance(default, bool):
            desc.integer_range = [IntegerRange(from_value=int(max(lo, -2**63)),
                                               to_value=int(min(hi, 2**63 - 1)), step=0)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    try:
        value = node.declare_parameter(name, default, desc).value
    except Exception as exc:  # rclpy's own refusals (type, range) do not always name it
        raise ValueError(f"parameter {name!r}: {exc}") from None
    check_value(name, value, min_value=min_value, max_value=max_value, choices=choices,
                open_min=open_min, open_max=open_max)
    return value


def declare_spec(node, spec: ParamSpec) -> Any:
    """Declare one :class:`ParamSpec` (read-only unless ``spec.live``); its value."""
    return declare(node, spec.name, spec.default, spec.description, read_only=not spec.live,
                   min_value=spec.min_value, max_value=spec.max_value, choices=spec.choices,
                   open_min=spec.open_min, open_max=spec.open_max)


def config_file(package: str, node_name: str) -> Path:
    """The installed parameter file ``share/<package>/config/<node_name>.yaml``."""
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory(package)) / "config" / f"{node_name}.yaml"


def config_parameters(package: str, node_name: str) -> dict:
    """The ``ros__parameters`` of :func:`config_file` (the node's shipped defaults)."""
    import yaml

    return dict(yaml.safe_load(config_file(package, node_name).read_text())["/**"]
                ["ros__parameters"])


def _markdown_value(value) -> str:
    if isinstance(value, str):
        return f"`{value!r}`" if value == "" else f"`{value}`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, (list, tuple)):
        return "`[" + ", ".join(str(v) for v in value) + "]`"
    return f"`{value}`"


def parameter_table(node) -> str:
    """Markdown table of the parameters ``node`` declared (name, default, when a change
    applies, description with range / choices), in declaration order: the package
    READMEs' tables are this output (checked by the tests), so a parameter is described
    once, where it is declared."""
    rows = ["| parameter | default | change | description |", "|---|---|---|---|"]
    for name, param in node._parameters.items():
        if name in RCLPY_PARAMETERS:
            continue
        d = node.describe_parameter(name)
        text = d.description.removesuffix(_LIVE).removesuffix(_READ_ONLY)
        ranges = list(d.floating_point_range) + list(d.integer_range)
        if d.additional_constraints.startswith("Range"):
            text += " " + d.additional_constraints  # an open range: ROS ranges are closed
            ranges = []
        elif d.additional_constraints:
            text += f" ({d.additional_constraints})"
        for r in ranges:
            lo, hi = (("-inf" if v <= -2**63 or v == -math.inf else
                       "inf" if v >= 2**63 - 1 or v == math.inf else f"{v:g}")
                      for v in (r.from_value, r.to_value))
            text += f" Range [{lo}, {hi}]."
        change = "restart" if d.read_only else "live"
        rows.append(f"| `{name}` | {_markdown_value(param.value)} | {change} | "
                    + text.replace("|", "\\|") + " |")
    return "\n".join(rows) + "\n"
