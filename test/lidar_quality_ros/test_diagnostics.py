from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lidar_quality_ros.diagnostics import NodeDiagnostics
from rclpy.node import Node


class _DiagNode(Node):
    def __init__(self, **kwargs):
        super().__init__("diag_node", **kwargs)
        self.diag = NodeDiagnostics(self, "work", period_s=0.1)


def _values(status):
    return {v.key: v.value for v in status.values}


def test_counts_rates_and_levels(ros):
    col = ros.collector(DiagnosticArray, "/diagnostics")
    node = ros.start(_DiagNode)
    d = node.diag
    for _ in range(4):
        d.input_received("input/points")
    d.frame_processed(2.0)
    d.frame_processed(4.0)
    d.frame_dropped("malformed_cloud")
    d.add_source(lambda: {"sync.matched": 2}, lambda: 3)
    status = d.status()
    v = _values(status)
    assert status.name == "diag_node: work" and status.level == DiagnosticStatus.OK
    assert v["frames_out"] == "2" and v["received.input/points"] == "4"
    assert v["dropped"] == "4" and v["dropped.malformed_cloud"] == "1"  # 1 own + 3 upstream
    assert d.dropped == 4
    assert float(v["processing_ms_p50"]) == 3.0
    assert v["sync.matched"] == "2"
    d.warn("cloud", "bad cloud")
    assert d.status().level == DiagnosticStatus.WARN and d.status().message == "bad cloud"
    d.clear("cloud")
    assert d.status().level == DiagnosticStatus.OK
    assert col.wait_for(2, timeout=10.0)
    assert any(s.name == "diag_node: work" for m in col.messages for s in m.status)
