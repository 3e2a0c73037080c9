"""Stamp-synchronised subscriptions over real DDS: approximate matching, loss accounting."""
import time

from lidar_quality_ros.diagnostics import NodeDiagnostics
from lidar_quality_ros.synced_inputs import SyncedInputs
from rclpy.node import Node
from geometry_msgs.msg import PointStamped
from node_shell_checks import wait_until


class _Pair(Node):
    def __init__(self, **kwargs):
        super().__init__("pair_node", **kwargs)
        self.sets = []
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointStamped, "a"), (PointStamped, "b")], self.sets.append,
                                   mode="approximate", slop_s=0.01, diagnostics=self.diag)


def _h(sec, nsec):
    m = PointStamped()
    m.header.frame_id = f"{sec}.{nsec}"
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    return m


def test_approximate_pairs_and_counts(ros):
    node = ros.start(_Pair)
    pa, pb = ros.sensor_publisher(PointStamped, "a"), ros.sensor_publisher(PointStamped, "b")
    assert ros.wait_for_match(pa) and ros.wait_for_match(pb)
    pa.publish(_h(1, 0))
    time.sleep(0.05)
    pb.publish(_h(1, 5_000_000))       # 5 ms apart: a match
    time.sleep(0.05)
    pa.publish(_h(2, 0))
    time.sleep(0.05)
    pb.publish(_h(2, 50_000_000))      # 50 ms apart: no match
    time.sleep(0.05)
    pa.publish(_h(3, 0))
    time.sleep(0.05)
    pb.publish(_h(3, 0))
    assert wait_until(lambda: len(node.sets) == 2 and node.inputs.unmatched_dropped() == 2)
    assert [tuple(m.header.frame_id for m in s.messages) for s in node.sets] == [
        ("1.0", "1.5000000"), ("3.0", "3.0")]
    # a@2.0 and b@2.05 were superseded by the frame-3 match: both counted as lost
    assert node.inputs.unmatched_dropped() == 2
    assert node.diag.dropped == 2


class _Failing(Node):
    def __init__(self, **kwargs):
        super().__init__("failing_node", **kwargs)
        self.calls = 0
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self._boom,
                                   diagnostics=self.diag)

    def _boom(self, synced):
        self.calls += 1
        raise RuntimeError("feature code bug")


def test_callback_exception_is_contained_and_counted(ros):
    node = ros.start(_Failing)
    pub = ros.sensor_publisher(PointStamped, "a")
    assert ros.wait_for_match(pub)
    for sec in (1, 2):
        pub.publish(_h(sec, 0))
        time.sleep(0.05)
    assert wait_until(lambda: node.diag.dropped == 2)
    assert node.calls == 2  # the node survived the first exception
    assert "feature code bug" in node.diag.status().message
