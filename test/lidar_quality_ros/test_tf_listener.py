"""TfListener on real rclpy: a /tf_static latched before the listener starts arrives
(transient local), /tf samples interpolate, refused entries are reported, tf2's QoS."""
import time

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from lidar_quality_core.transforms import ExtrapolationError, Transform
from lidar_quality_ros.tf_listener import TfListener, tf_qos, tf_static_qos
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

pytest_plugins = ["lidar_quality_ros.testing"]


def ts(parent, child, sec, nsec, xyz, q=(0.0, 0.0, 0.0, 1.0)):
    m = TransformStamped()
    m.header.frame_id, m.child_frame_id = parent, child
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    m.transform.translation.x, m.transform.translation.y, m.transform.translation.z = xyz
    r = m.transform.rotation
    r.x, r.y, r.z, r.w = q
    return m


def wait(pred, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_static_latched_and_dynamic_samples(ros):
    static_pub = ros.publisher(TFMessage, "/tf_static", tf_static_qos())
    q = (0.0, 0.0, np.sin(0.05), np.cos(0.05))
    static_pub.publish(TFMessage(transforms=[ts("base_link", "lidar_top", 0, 0,
                                                (1.2, 0.0, 1.8), q)]))
    bad = []
    listener = TfListener(ros.node, on_bad=bad.append)  # created after the publication
    assert wait(lambda: listener.buffer.can_transform("base_link", "lidar_top"))
    t = listener.buffer.lookup("lidar_top", "base_link", 123)
    assert t.close_to(Transform([1.2, 0, 1.8], q).inverse())

    pub = ros.publisher(TFMessage, "/tf", tf_qos())
    assert ros.wait_for_match(pub)
    pub.publish(TFMessage(transforms=[ts("odom", "base_link", 10, 0, (0.0, 0.0, 0.0))]))
    pub.publish(TFMessage(transforms=[ts("odom", "base_link", 10, 100_000_000, (1.0, 0, 0)),
                                      ts("odom", "bad", 10, 0, (0, 0, 0), (0, 0, 0, 0))]))
    assert wait(lambda: listener.received["dynamic"] == 3)
    mid = listener.buffer.lookup("odom", "lidar_top", 10_050_000_000)
    np.testing.assert_allclose(mid.translation, [0.5 + 1.2, 0.0, 1.8], atol=1e-12)
    with pytest.raises(ExtrapolationError, match="'lidar_top' to 'odom' at stamp 11.0"):
        listener.buffer.lookup("odom", "lidar_top", 11_000_000_000)
    assert len(bad) == 1 and "/tf refused" in bad[0] and "'bad'" in bad[0]
    listener.destroy()


def test_qos_is_tf2s(ros):
    listener = TfListener(ros.node)
    infos = {s.topic_name: s.qos_profile for s in listener.subscriptions}
    assert infos["/tf_static"].durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert infos["/tf"].durability == DurabilityPolicy.VOLATILE
    assert all(p.reliability == ReliabilityPolicy.RELIABLE and p.depth == 100
               for p in infos.values())
