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
