"""Perception bag frames: grouping by header stamp, heads, missing topics."""
import numpy as np
import pytest
from lidar_quality_core.boxes import arrays_to_detections
from lidar_quality_core.pointcloud import create_xyz_cloud
from lidar_quality_ros.bag_io import BagWriter, read_bag
from lidar_quality_ros.perception_bag import (bag_group, head_count, parse_topic_options,
                                              perception_frames, resolve_bags, topic_of)
from std_msgs.msg import Header

DET = "vision_msgs/msg/Detection3DArray"
PC = "sensor_msgs/msg/PointCloud2"


def _write(path, n=5, shuffle_log=False):
    with BagWriter(path) as w:
        for i in range(n):
            h = Header(frame_id="lidar")
            h.stamp.sec, h.stamp.nanosec = 100 + i // 10, (i % 10) * 100_000_000
            t = h.stamp.sec * 10**9 + h.stamp.nanosec
            cloud = create_xyz_cloud(h, np.full((3, 3), i, np.float32))
            boxes = np.array([[i, 0, 0, 4, 2, 1.5, 0.0]])
            dets = arrays_to_detections(h, boxes, ["car"], [0.5], ids=[f"d{i}"])
            # outputs logged later than their scan, as a recorder does
            w.write("/lidar/points", PC, t, cloud)
            w.write("/perception/detections", DET, t + 250_000_000, dets)
            w.write("/perception/head_0", DET, t + 260_000_000, dets)
            w.write("/perception/head_1", DET, t + 270_000_000, dets)


def test_frames_grouped_by_stamp(tmp_path):
    _write(tmp_path / "b", n=25)
    assert head_count(tmp_path / "b") == 2
    # outputs lag 2.5 scans: a window of 3 newer stamps is enough
    frames = list(perception_frames(tmp_path / "b", heads=None, window=3))
    assert [f.index for f in frames] == list(range(25))
    for i, f in enumerate(frames):
        assert f.detections.detections[0].id == f"d{i}"
        assert f.points.header.stamp == f.detections.header.stamp
        assert [h.detections[0].id for h in f.heads] == [f"d{i}", f"d{i}"]
        assert f.head_variances == [None, None] and f.proposals is None
    assert np.diff([f.stamp_ns for f in frames]).min() > 0


def test_missing_required_topic(tmp_path):
    _write(tmp_path / "b", n=1)
    with pytest.raises(ValueError, match="no topic"):
        list(perception_frames(tmp_path / "b", topics={"points": "/other"}))
    with pytest.raises(ValueError, match="unknown"):
        list(perception_frames(tmp_path / "b", want=("nope",)))


def test_resolve_bags_and_groups(tmp_path):
    for name in ("seq_01", "seq_00"):
        (tmp_path / "split" / name).mkdir(parents=True)
        (tmp_path / "split" / name / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (tmp_path / "split" / "notes").mkdir()
    bags = resolve_bags([tmp_path / "split"])
    assert [b.name for b in bags] == ["seq_00", "seq_01"]
    assert resolve_bags([bags[1]]) == [bags[1]]
    assert bag_group(bags[1]) == "split/seq_01"
    with pytest.raises(FileNotFoundError, match="not a rosbag2"):
        resolve_bags([tmp_path / "split" / "notes"])


def test_topic_keys_and_options():
    assert topic_of("points") == "/lidar/points"
    assert topic_of("head_3/variance") == "/perception/head_3/variance"
    assert topic_of("head_12") == "/perception/head_12"
    assert topic_of("points", {"points": "/a"}) == "/a"
    assert parse_topic_options(["points=/sensing/lidar/top/pointcloud", "head_0/variance=/v"]) \
        == {"points": "/sensing/lidar/top/pointcloud", "head_0/variance": "/v"}
    for bad, why in (("cloud=/a", "unknown topic key 'cloud' (known: points, points_gt, "
                                  "gt_objects, detections, proposals, segmentation, head_<k>, "
                                  "head_<k>/variance)"),
                     ("head_x=/a", "unknown topic key 'head_x'"),
                     ("points", "expected KEY=/topic/name"),
                     ("points=lidar", "expected KEY=/topic/name")):
        with pytest.raises(ValueError) as e:
            parse_topic_options([bad])
        assert why in str(e.value)
    with pytest.raises(ValueError, match="given twice"):
        parse_topic_options(["points=/a", "points=/b"])


def test_frames_under_other_names_and_unknown_types(tmp_path, capsys):
    """``topics`` names every topic (heads too); a topic of a type unknown here is left
    out with one warning per type."""
    _write(tmp_path / "b")
    names = {"points": "/sensing/lidar/top/pointcloud", "detections": "/objects",
             "head_0": "/member_0", "head_1": "/member_1"}
    with BagWriter(tmp_path / "u") as w:
        for m in read_bag(tmp_path / "b"):
            key = next(k for k in names if topic_of(k) == m.topic)
            w.write(names[key], m.msgtype, m.stamp_ns, m.raw)
            w.write("/packets", "velodyne_msgs/msg/VelodyneScan", m.stamp_ns, b"\0\1\0\0" * 4)
    ref = list(perception_frames(tmp_path / "b", want=("points", "detections"), heads=None))
    got = list(perception_frames(tmp_path / "u", want=("points", "detections"), heads=None,
                                 topics=names))
    assert head_count(tmp_path / "u", names) == 2 and head_count(tmp_path / "u") == 0
    assert [(f.stamp_ns, f.points, f.detections, f.heads) for f in got] == [
        (f.stamp_ns, f.points, f.detections, f.heads) for f in ref]
    with pytest.raises(ValueError, match="unknown topic key"):
        list(perception_frames(tmp_path / "u", topics={"cloud": "/x"}))
    capsys.readouterr()
    # a driver's packets named as the cloud: said, not a traceback
    with pytest.raises(ValueError, match="VelodyneScan, which is not available here"):
        list(perception_frames(tmp_path / "u", topics={"points": "/packets"}))
    assert capsys.readouterr().err.count("velodyne_msgs/msg/VelodyneScan") == 1
