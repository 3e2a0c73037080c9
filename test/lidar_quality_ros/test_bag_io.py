import numpy as np
import pytest
from lidar_quality_core.pointcloud import create_xyz_cloud, xyz_intensity
from lidar_quality_msgs.msg import BoxVariance, BoxVarianceArray
from std_msgs.msg import Header
from vision_msgs.msg import Detection3D, Detection3DArray

from lidar_quality_ros.bag_io import BagWriter, bag_topics, message_class, read_bag


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_write_read_round_trip(tmp_path, storage):
    h = Header(frame_id="lidar")
    h.stamp.sec = 3
    xyz = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    cloud = create_xyz_cloud(h, xyz)
    dets = Detection3DArray(header=h, detections=[Detection3D(id="7")])
    var = BoxVarianceArray(header=h, variances=[BoxVariance(detection_id="7", yaw=0.5)])
    with BagWriter(tmp_path / "b", storage=storage) as w:
        w.write("/pts", "sensor_msgs/msg/PointCloud2", 10, cloud)
        w.write("/dets", "vision_msgs/msg/Detection3DArray", 11, dets)
        w.write("/var", "lidar_quality_msgs/msg/BoxVarianceArray", 12, var)
    assert bag_topics(tmp_path / "b") == {"/pts": "sensor_msgs/msg/PointCloud2",
                                          "/dets": "vision_msgs/msg/Detection3DArray",
                                          "/var": "lidar_quality_msgs/msg/BoxVarianceArray"}
    msgs = list(read_bag(tmp_path / "b"))
    assert [(m.topic, m.stamp_ns) for m in msgs] == [("/pts", 10), ("/dets", 11), ("/var", 12)]
    np.testing.assert_array_equal(xyz_intensity(msgs[0].decode())[0], xyz)
    assert msgs[1].decode() == dets and msgs[2].decode() == var
    # raw pass-through keeps the bytes
    with BagWriter(tmp_path / "c", storage=storage) as w:
        w.write("/var", msgs[2].msgtype, msgs[2].stamp_ns, msgs[2].raw)
    assert next(read_bag(tmp_path / "c")).raw == msgs[2].raw


def test_rosbags_typestore_reads_our_bag(tmp_path):
    """A reader that does not use rclpy (rosbags' own CDR) decodes what we wrote."""
    from lidar_quality_core.rosbag_types import typestore
    from rosbags.rosbag2 import Reader

    var = BoxVarianceArray(variances=[BoxVariance(detection_index=2, length=1.5)])
    with BagWriter(tmp_path / "b") as w:
        w.write("/var", "lidar_quality_msgs/msg/BoxVarianceArray", 1, var)
    ts = typestore()
    with Reader(tmp_path / "b") as r:
        (conn, _, raw), = list(r.messages())
        msg = ts.deserialize_cdr(raw, conn.msgtype)
    assert msg.variances[0].detection_index == 2 and msg.variances[0].length == 1.5


def test_message_class_and_bad_storage(tmp_path):
    assert message_class("vision_msgs/msg/Detection3DArray") is Detection3DArray
    with pytest.raises(ValueError, match="storage"):
        BagWriter(tmp_path / "x", storage="zip")
