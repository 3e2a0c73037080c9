"""Serialized messages published from our own buffers through rcl, over real DDS."""
import numpy as np
import pytest
from rclpy.exceptions import InvalidHandle
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from lidar_quality_core.pointcloud import create_xyz_cloud
from lidar_quality_ros import rcl_api
from lidar_quality_ros import serialized_publish as sp
from lidar_quality_ros.serialized_publish import is_serialized, publish_serialized


def _cloud(sec: int, n: int = 3000, seed: int = 0) -> PointCloud2:
    rng = np.random.default_rng(seed)
    h = Header(frame_id="lidar")
    h.stamp.sec = sec
    return create_xyz_cloud(h, rng.normal(size=(n, 3)).astype(np.float32),
                            rng.random(n).astype(np.float32))


@pytest.fixture(params=["from the buffer", "through rclpy"])
def pub_and_received(ros, request, monkeypatch):
    """(publisher, collector of the messages a subscriber in the same graph receives), for
    messages published from their buffer (every size) or by rclpy (below MIN_BYTES)."""
    assert rcl_api.load() is not None, rcl_api.why_not()  # rclpy is here, so rcl is
    monkeypatch.setattr(sp, "MIN_BYTES", 0 if request.param == "from the buffer" else 1 << 40)
    got = ros.collector(PointCloud2, "published_raw")
    pub = ros.publisher(PointCloud2, "published_raw")
    assert ros.wait_for_match(pub)
    return pub, got


def test_large_messages_go_from_their_buffer_small_ones_through_rclpy(ros):
    got = ros.collector(PointCloud2, "published_raw")
    pub = ros.publisher(PointCloud2, "published_raw")
    assert ros.wait_for_match(pub)
    through_rclpy = []
    rclpy_publish = pub.publish
    pub.publish = lambda m: (through_rclpy.append(len(m)), rclpy_publish(m))
    small, large = _cloud(1, n=1000), _cloud(2, n=sp.MIN_BYTES // 16 + 1)
    for m in (small, large):
        publish_serialized(pub, serialize_message(m))
    assert got.wait_for(2, timeout=10.0) and got.messages == [small, large]
    assert through_rclpy == [len(serialize_message(small))]


def test_every_bytes_like_arrives_as_the_message(pub_and_received):
    pub, got = pub_and_received
    msgs = [_cloud(k, seed=k) for k in range(4)]
    wires = [serialize_message(m) for m in msgs]
    big = np.frombuffer(b"\xee" * 5 + wires[3] + b"\xee" * 3, np.uint8)
    sent = [wires[0], bytearray(wires[1]), memoryview(wires[2]), big[5:-3]]  # a view inside
    assert all(is_serialized(s) for s in sent) and not is_serialized(msgs[0])
    for s in sent:
        publish_serialized(pub, s)
    assert got.wait_for(4, timeout=10.0)
    assert got.messages == msgs   # in order, each the message serialized


def test_a_buffer_changed_after_publishing_does_not_change_what_was_sent(pub_and_received):
    # rcl copies the bytes into the middleware before it returns: the node may reuse them
    pub, got = pub_and_received
    m = _cloud(7)
    buf = np.frombuffer(bytearray(serialize_message(m)), np.uint8)
    publish_serialized(pub, buf)
    buf[-100:] = 0
    assert got.wait_for(1, timeout=10.0)
    assert got.messages[0] == m


def test_what_is_not_contiguous_bytes_is_refused_a_destroyed_publisher_raises(
        ros, pub_and_received):
    pub, _ = pub_and_received
    wire = np.frombuffer(serialize_message(_cloud(1)), np.uint8)
    with pytest.raises(TypeError, match="contiguous bytes"):
        publish_serialized(pub, wire[::2])
    with pytest.raises(TypeError, match="contiguous bytes"):
        publish_serialized(pub, wire.view(np.int8))
    ros.node.destroy_publisher(pub)
    with pytest.raises(InvalidHandle):   # as rclpy's publish raises
        publish_serialized(pub, wire)
