"""reference-perception offline: a simulated bag becomes a perception bag; KITTI and
SemanticKITTI result files."""
import numpy as np
import pytest
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.pointcloud import read_fields, xyz_intensity
from lidar_quality_ros.bag_io import bag_topics, read_bag
from lidar_sim.classes import CLASS_NAMES
from lidar_sim.cli import main as sim_main

from reference_perception.cli import main
from reference_perception.messages import probability_field


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "sim"
    assert sim_main(["generate", "--sequences", "1", "--frames", "2", "--seed", "5",
                     "--out", str(out), "--quiet", "--val-sequences", "0"]) == 0
    return out


def test_perception_bag(sim_dir, tmp_path):
    out = tmp_path / "perception"
    assert main(["bag", "--in", str(sim_dir / "bags" / "seq_00"), "--out", str(out), "--quiet",
                 "--kitti-results", str(tmp_path / "kitti_res")]) == 0
    topics = bag_topics(out)
    src = bag_topics(sim_dir / "bags" / "seq_00")
    assert src.items() <= topics.items()               # every input topic copied
    for t in ("detections", "proposals", "segmentation", "head_0", "head_1", "head_0/variance",
              "head_1/variance"):
        assert f"/perception/{t}" in topics
    msgs = list(read_bag(out))
    clouds = [m for m in msgs if m.topic == "/lidar/points"]
    assert len(clouds) == 2
    for c in clouds:
        same = {m.topic: m for m in msgs if m.stamp_ns == c.stamp_ns}
        cloud = c.decode()
        seg = same["/perception/segmentation"].decode()
        assert seg.header == cloud.header and seg.width == cloud.width
        np.testing.assert_array_equal(xyz_intensity(seg)[0], xyz_intensity(cloud)[0])
        p = read_fields(seg, [probability_field(n) for n in CLASS_NAMES])
        np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-4)
        dets = detections_to_arrays(same["/perception/detections"].decode())
        props = detections_to_arrays(same["/perception/proposals"].decode())
        assert set(dets.ids) <= set(props.ids) and len(dets) > 0
        assert same["/perception/head_1"].decode().header == cloud.header
    # raw input messages are copied byte for byte
    src_msgs = {(m.topic, m.stamp_ns): m.raw for m in read_bag(sim_dir / "bags" / "seq_00")}
    assert all(src_msgs[(m.topic, m.stamp_ns)] == m.raw for m in msgs if m.topic in src)
    res = sorted((tmp_path / "kitti_res").glob("*.txt"))
    assert [r.name for r in res] == ["000000.txt", "000001.txt"]
    lines = [l.split() for r in res for l in r.read_text().splitlines()]
    assert lines and all(len(l) == 16 and l[0] in ("Car", "Truck", "Pedestrian", "Cyclist") for l in lines)


def test_kitti_and_semantickitti_dirs(sim_dir, tmp_path):
    assert main(["kitti", "--root", str(sim_dir / "kitti"), "--out", str(tmp_path / "k"),
                 "--heads", "2", "--no-segmenter", "--quiet"]) == 0
    assert len(list((tmp_path / "k").glob("*.txt"))) == 2
    z = np.load(sorted((tmp_path / "k" / "head_1").glob("*.npz"))[0])
    assert z["boxes"].shape[1] == 7 and z["variances"].shape == z["boxes"].shape
    assert main(["semantickitti", "--root", str(sim_dir / "semantickitti"), "--out",
                 str(tmp_path / "s"), "--quiet"]) == 0
    seq = tmp_path / "s" / "sequences" / "00"
    scan = np.fromfile(sim_dir / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin", "<f4")
    labels = np.fromfile(seq / "predictions" / "000000.label", "<u4")
    probs = np.load(seq / "probabilities" / "000000.npy")
    assert len(labels) == len(scan) // 4 == len(probs)
    assert probs.shape[1] == len(CLASS_NAMES)
    from lidar_sim.classes import from_semantickitti
    np.testing.assert_array_equal(from_semantickitti(labels & 0xFFFF), probs.argmax(axis=1))
