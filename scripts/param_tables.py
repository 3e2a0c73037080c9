"""Write the parameter table of each node package's README from the node's own
declarations (``lidar_quality_ros.params.parameter_table``): a parameter is described once,
where it is declared. Run after changing a declaration (the tests check the tables):

    bash scripts/with_env.sh python scripts/param_tables.py
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import rclpy
from rclpy.context import Context

ROOT = Path(__file__).resolve().parents[1]
BEGIN = "<!-- parameters: written by scripts/param_tables.py from the declarations -->\n"
END = "<!-- end of parameters -->\n"
NODES = {"lmd_ros": "lmd_ros.lmd_node:LmdNode", "lms_ros": "lms_ros.lms_node:LmsNode",
         "mimo_ros": "mimo_ros.mimo_node:MimoNode"}


def node_table(spec: str) -> str:
    """The parameter table of the node class ``module:Class`` started with its defaults."""
    import importlib

    from lidar_quality_ros.params import parameter_table

    module, cls = spec.split(":")
    node_cls = getattr(importlib.import_module(module), cls)
    ctx = Context()
    rclpy.init(context=ctx)  # the environment's domain: with_env.sh keeps it private, on loopback
    try:
        node = node_cls(context=ctx, start_parameter_services=False)
        try:
            return parameter_table(node)
        finally:
            node.destroy_node()
    finally:
        ctx.try_shutdown()


def readme_table(text: str) -> str | None:
    m = re.search(re.escape(BEGIN) + r"(.*?)" + re.escape(END), text, re.S)
    return m.group(1) if m else None


def main() -> int:
    for pkg, spec in NODES.items():
        path = ROOT / pkg / "README.md"
        text = path.read_text()
        if readme_table(text) is None:
            sys.exit(f"{path}: no parameter section ({BEGIN.strip()} ... {END.strip()})")
        new = text.replace(BEGIN + readme_table(text) + END, BEGIN + node_table(spec) + END)
        path.write_text(new)
        print(f"{path.relative_to(ROOT)}: parameter table written")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
