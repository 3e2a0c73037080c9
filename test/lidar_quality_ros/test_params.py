import pytest
from lidar_quality_ros.params import declare
from rclpy.node import Node


class _ParamNode(Node):
    def __init__(self, **kwargs):
        super().__init__("param_node", **kwargs)
        self.rate = declare(self, "rate", 10.0, "Rate in Hz.", min_value=0.0, max_value=100.0)
        self.mode = declare(self, "mode", "a", "Mode.", choices=("a", "b"))
        self.n = declare(self, "n", 3, "Count.", min_value=1)


def test_described_and_overridable(ros):
    node = ros.start(_ParamNode, parameters={"rate": 20.0, "mode": "b"})
    assert (node.rate, node.mode, node.n) == (20.0, "b", 3)
    for name in ("rate", "mode", "n"):
        assert node.describe_parameter(name).description
    assert node.describe_parameter("mode").additional_constraints == "one of: a, b"


def test_bad_choice_rejected(ros):
    with pytest.raises(ValueError, match="mode"):
        ros.start(_ParamNode, parameters={"mode": "c"})


def test_out_of_range_rejected(ros):
    with pytest.raises(Exception, match="rate"):
        ros.start(_ParamNode, parameters={"rate": 500.0})


def test_description_required(ros):
    node = ros.start(_ParamNode)
    with pytest.raises(ValueError, match="description"):
        declare(node, "undescribed", 1, "")


@pytest.mark.parametrize("package", ["lmd_ros", "lms_ros", "mimo_ros"])
def test_package_readme_parameter_table_is_the_declarations(ros, package):
    # one description per parameter: the README table is written from the node's own
    # declarations (scripts/param_tables.py); a declaration changed without it fails here
    import importlib
    import sys
    from pathlib import Path

    from lidar_quality_ros.params import parameter_table

    root = Path(__file__).resolve().parents[2]
    sys.path.insert(0, str(root / "scripts"))
    try:
        import param_tables
    finally:
        sys.path.pop(0)
    module, cls = param_tables.NODES[package].split(":")
    node = ros.start(getattr(importlib.import_module(module), cls))
    readme = (root / package / "README.md").read_text()
    assert param_tables.readme_table(readme) == parameter_table(node), (
        f"{package}/README.md: run `bash scripts/with_env.sh python scripts/param_tables.py`")
    assert "| `use_sim_time`" not in readme
    for name in node._parameters:
        assert name in ("use_sim_time", "start_type_description_service") or f"| `{name}` |" in readme
