"""autoware_bag: a perception bag's Detection3DArray topics rewritten as DetectedObjects
(same boxes, classes, order and log times), every other message copied byte for byte."""
import numpy as np
from autoware_perception_msgs.msg import DetectedObjects
from lidar_quality_core.autoware_objects import objects_to_arrays
from lidar_quality_core.boxes import arrays_to_detections, detections_to_arrays
from lidar_quality_core.pointcloud import create_xyz_cloud
from lidar_quality_msgs.msg import BoxVarianceArray
from lidar_quality_ros.bag_io import BagWriter, bag_info, read_bag
from lidar_quality_tools.autoware_bag import OBJECTS, convert, main
from rclpy.serialization import deserialize_message
from reference_perception.messages import box_variance_array
from std_msgs.msg import Header


def _bag(path):
    rng = np.random.default_rng(3)
    sent = []
    with BagWriter(path) as w:
        for i in range(3):
            h = Header(frame_id="lidar")
            h.stamp.sec = 10 + i
            stamp = (10 + i) * 10**9
            boxes = np.column_stack([rng.uniform(-30, 30, (4, 2)), np.zeros(4),
                                     np.tile([4.0, 1.8, 1.5], (4, 1)), rng.uniform(-3, 3, 4)])
            dets = arrays_to_detections(h, boxes, ["car", "pedestrian", "cyclist", "truck"],
                                        rng.uniform(0.2, 0.9, 4), ids=[f"d{i}_{k}" for k in range(4)])
            w.write("/lidar/points", "sensor_msgs/msg/PointCloud2", stamp,
                    create_xyz_cloud(h, rng.normal(size=(50, 3)).astype(np.float32)))
            w.write("/perception/detections", "vision_msgs/msg/Detection3DArray", stamp, dets)
            w.write("/perception/head_0/variance", "lidar_quality_msgs/msg/BoxVarianceArray",
                    stamp, box_variance_array(h, np.full((4, 7), 0.1),
                                              ids=[f"d{i}_{k}" for k in range(4)]))
            sent.append(dets)
    return sent


def test_detections_become_objects_the_rest_is_copied(tmp_path):
    sent = _bag(tmp_path / "in")
    done = convert(tmp_path / "in", tmp_path / "out")
    assert done == {"/perception/detections": 3, "/perception/head_0/variance": 3}
    info = bag_info(tmp_path / "out")
    assert info.topics["/perception/detections"].msgtype == OBJECTS
    assert info.topics["/lidar/points"].msgtype == "sensor_msgs/msg/PointCloud2"
    src = {(m.topic, m.stamp_ns): m.raw for m in read_bag(tmp_path / "in")}
    got = list(read_bag(tmp_path / "out"))
    assert [(m.topic, m.stamp_ns) for m in got] == list(src)
    k = 0
    for m in got:
        if m.topic == "/lidar/points":
            assert m.raw == src[(m.topic, m.stamp_ns)]
            continue
        if m.topic.endswith("variance"):  # detections named by index, as objects have no id
            var = deserialize_message(m.raw, BoxVarianceArray).variances
            assert [v.detection_id for v in var] == ["0", "1", "2", "3"]
            assert [v.detection_index for v in var] == [0, 1, 2, 3] and var[0].x == 0.1
            continue
        objs = deserialize_message(m.raw, DetectedObjects)
        want = detections_to_arrays(sent[k])
        a = objects_to_arrays(objs)
        assert objs.header == sent[k].header
        np.testing.assert_allclose(a.boxes, want.boxes, atol=1e-9)
        assert a.labels == want.labels  # truck included: TRUCK <-> truck
        np.testing.assert_allclose(a.scores, want.scores, rtol=1e-6)  # float32
        np.testing.assert_allclose([o.existence_probability for o in objs.objects], want.scores,
                                   rtol=1e-6)
        k += 1
    assert k == 3 and not (tmp_path / "out.partial").exists()


def test_cli_refuses_what_is_not_a_bag(tmp_path, capsys):
    assert main(["--bag", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert "not a rosbag2 directory" in capsys.readouterr().err
