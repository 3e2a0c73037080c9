import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lidar_quality_ros.diagnostics import NodeDiagnostics
from rclpy.node import Node

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


class _DiagNode(Node):
    def __init__(self, **kwargs):
        super().__init__("diag_node", **kwargs)
        self.diag = NodeDiagnostics(self, "work", period_s=0.1, window_s=0.5, hold_s=0.3)


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
    # 4 of 6 frames lost: above drop_warn, but too few frames to call it an error
    assert status.name == "diag_node: work" and status.level == WARN
    assert "4 of 6 frames lost" in status.message
    assert v["frames_out"] == "2" and v["received.input/points"] == "4"
    assert v["dropped"] == "4" and v["dropped.malformed_cloud"] == "1"  # 1 own + 3 upstream
    assert d.dropped == 4
    assert float(v["processing_ms_p50"]) == 3.0
    assert v["sync.matched"] == "2"
    d.set_value("scheduling", "normal")
    d.set_values([("boxes.in", 7), ("drift.level", "OK"), ("scheduling", "SCHED_FIFO 10")])
    v = _values(d.status())
    assert (v["boxes.in"], v["drift.level"], v["scheduling"]) == ("7", "OK", "SCHED_FIFO 10")
    time.sleep(0.6)  # the losses leave the window
    d.status()
    assert d.status().level == OK
    d.warn("cloud", "bad cloud")
    assert d.status().level == WARN and d.status().message == "bad cloud"
    d.clear("cloud")
    # a cleared warning is still shown for hold_s: a problem between two publications shows
    assert d.status().level == WARN
    time.sleep(0.35)
    assert d.status().level == OK and _values(d.status())["warnings.cloud"] == "1"
    assert col.wait_for(2, timeout=10.0)
    assert any(s.name == "diag_node: work" for m in col.messages for s in m.status)


def test_drop_fraction_error_and_warning_levels(ros):
    d = ros.start(_DiagNode).diag
    d.warn("frame_id", "frame_id mismatch", ERROR)
    d.warn("cloud", "bad cloud")
    s = d.status()  # the worst level wins; its message first
    assert s.level == ERROR and s.message == "frame_id mismatch; bad cloud"
    d.clear("frame_id")
    d.clear("cloud")
    time.sleep(0.35)
    for _ in range(8):
        d.frame_processed(1.0)
    d.frame_dropped("overrun", 4)  # 4 of 12: above drop_error with enough frames
    s = d.status()
    assert s.level == ERROR and "4 of 12 frames lost" in s.message, s.message
    assert _values(s)["dropped_fraction_window"] == "0.333"


def test_processing_slower_than_the_input_warns(ros):
    d = ros.start(_DiagNode).diag
    for _ in range(10):
        d.input_received("input/points")
        d.frame_processed(80.0)  # 80 ms per frame, inputs every ~10 ms
        time.sleep(0.01)
    s = d.status()
    assert s.level == WARN and "cannot keep up" in s.message, s.message


def test_processing_time_limits_warn_and_error(ros):
    """processing_warn_ms / processing_error_ms (Autoware's processing-time diagnostics):
    the median of the recent frames against each limit; off (0) by default."""
    node = ros.start(_DiagNode)
    d = NodeDiagnostics(node, "timed", period_s=0, processing_warn_ms=20.0,
                        processing_error_ms=50.0)
    for ms in (5.0, 8.0, 6.0):
        d.frame_processed(ms)
    s = d.status()
    assert s.level == OK and _values(s)["processing_ms_recent"] == "6.000", s.message
    for _ in range(6):
        d.frame_processed(30.0)
    s = d.status()
    assert s.level == WARN and "above processing_warn_ms = 20 ms" in s.message, s.message
    for _ in range(20):
        d.frame_processed(70.0)
    s = d.status()
    assert s.level == ERROR and "above processing_error_ms = 50 ms" in s.message, s.message
    assert "processing_warn_ms" not in s.message  # the worse limit only
    off = NodeDiagnostics(node, "untimed", period_s=0)
    for _ in range(20):
        off.frame_processed(70.0)
    assert off.status().level == OK and "processing_ms_recent" not in _values(off.status())
