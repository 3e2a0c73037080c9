"""Serialized messages taken through rcl into buffers of our own, over real DDS."""
import gc
import time

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from lidar_quality_core.cloud_cdr import decode_point_cloud
from lidar_quality_core.pointcloud import create_xyz_cloud, xyz_intensity
from lidar_quality_ros.qos import SENSOR_QOS
from lidar_quality_ros.serialized_take import BufferTaker, available
from lidar_quality_ros.synced_inputs import ReadByInputReader


def _cloud(sec: int, n: int = 2000, seed: int = 0) -> PointCloud2:
    rng = np.random.default_rng(seed)
    h = Header(frame_id="lidar")
    h.stamp.sec = sec
    return create_xyz_cloud(h, rng.normal(size=(n, 3)).astype(np.float32),
                            rng.random(n).astype(np.float32))


@pytest.fixture
def raw_sub(ros):
    """(publisher, raw subscription no executor takes from) on one topic."""
    ok, why = available()
    assert ok, why  # rclpy is here, so rcl is: this must work on every supported install
    group = ReadByInputReader()
    sub = ros.node.create_subscription(PointCloud2, "take_me", lambda m: None, SENSOR_QOS,
                                       callback_group=group, raw=True)
    pub = ros.sensor_publisher(PointCloud2, "take_me")
    assert ros.wait_for_match(pub)
    yield pub, sub
    ros.node.destroy_subscription(sub)


def _take(taker, sub, timeout=10.0):
    deadline = time.monotonic() + timeout
    with sub.handle:
        while time.monotonic() < deadline:
            got = taker.take(sub.handle.pointer)
            if got is not None:
                return got
            time.sleep(0.005)
    raise AssertionError("nothing arrived")


def test_the_bytes_taken_are_the_serialized_message_read_only_and_in_place(raw_sub):
    pub, sub = raw_sub
    taker = BufferTaker()
    with sub.handle:
        assert taker.take(sub.handle.pointer) is None  # nothing sent yet: nothing taken
    msg = _cloud(1)
    pub.publish(msg)
    got = _take(taker, sub)
    assert got.dtype == np.uint8 and not got.flags.writeable
    # the message as sent (compared deserialized: CDR padding bytes are not defined)
    assert len(got) == len(serialize_message(msg))
    assert deserialize_message(got.tobytes(), PointCloud2) == msg
    cloud = decode_point_cloud(got)
    assert not cloud.data.flags.writeable
    assert np.shares_memory(cloud.data, got)  # the points read in place, not copied
    xyz, inten = xyz_intensity(cloud)
    ref = xyz_intensity(msg)
    assert np.array_equal(xyz, ref[0]) and np.array_equal(inten, ref[1])
    taker.close()


def test_a_buffer_is_reused_only_once_nothing_refers_to_its_view(raw_sub):
    pub, sub = raw_sub
    taker = BufferTaker(max_buffers=2)
    pub.publish(_cloud(1, seed=1))
    first = decode_point_cloud(_take(taker, sub))  # only a view of the view is kept
    assert taker.lent() == 1
    pub.publish(_cloud(2, n=5000, seed=2))  # larger: its buffer grows
    second = _take(taker, sub)
    assert taker.lent() == 2
    # both lent, the third message is not taken here (the caller takes it another way)
    pub.publish(_cloud(3, seed=3))
    time.sleep(0.2)
    with sub.handle:
        assert taker.take(sub.handle.pointer) is NotImplemented
    assert taker.all_lent == 1
    # the first message is intact while the second and later ones came in
    assert first.header.stamp.sec == 1
    assert np.array_equal(xyz_intensity(first)[0], xyz_intensity(_cloud(1, seed=1))[0])
    del first
    gc.collect()
    third = _take(taker, sub)  # the first buffer again, now free
    assert decode_point_cloud(third).header.stamp.sec == 3
    assert decode_point_cloud(second).header.stamp.sec == 2
    assert np.array_equal(xyz_intensity(decode_point_cloud(second))[0],
                          xyz_intensity(_cloud(2, n=5000, seed=2))[0])
    del second, third
    gc.collect()
    assert taker.lent() == 0
    taker.close()


def test_max_buffers_must_be_positive():
    with pytest.raises(ValueError, match="max_buffers"):
        BufferTaker(max_buffers=0)
