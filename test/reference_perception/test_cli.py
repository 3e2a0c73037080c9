"""reference-perception offline: a simulated bag becomes a perception bag; KITTI and
SemanticKITTI result files (KITTI results in each frame's own camera frame, read back to
the detector's lidar boxes by lmd_ros)."""
import shutil

import numpy as np
import pytest
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.pointcloud import read_fields, xyz_intensity
from lidar_quality_ros.bag_io import bag_topics, read_bag
from lidar_sim.classes import CLASS_NAMES
from lidar_sim.cli import main as sim_main

from realdata import require_realdata_kitti
from reference_perception.cli import Perception, main
from reference_perception.messages import probability_field
from sensor_msgs.msg import PointField


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
        # uint8 probability fields by default: round(p * 255), each off by <= half a step
        names = [probability_field(n) for n in CLASS_NAMES]
        assert {f.datatype for f in seg.fields if f.name in names} == {PointField.UINT8}
        p = read_fields(seg, names) / 255.0
        np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=len(names) * 0.5 / 255 + 1e-6)
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
    # a bag has no camera: the simulator's calibration, recorded beside the results
    from lidar_sim.kitti import SIM_CALIB
    assert all((tmp_path / "kitti_res" / "calib" / r.name).read_text() == SIM_CALIB.text()
               for r in res)


def test_kitti_and_semantickitti_dirs(sim_dir, tmp_path):
    assert main(["kitti", "--root", str(sim_dir / "kitti"), "--out", str(tmp_path / "k"),
                 "--heads", "2", "--no-segmenter", "--quiet"]) == 0
    assert len(list((tmp_path / "k").glob("*.txt"))) == 2
    for d in (tmp_path / "k", tmp_path / "k" / "head_1"):  # the calibration used, recorded
        for r in d.glob("*.txt"):
            assert (d / "calib" / r.name).read_text() == \
                (sim_dir / "kitti" / "training" / "calib" / r.name).read_text()
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


# ------------------------------------------------------------------ KITTI calibration
def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def assert_written_boxes(written, boxes, tol=0.01):
    """Every box read back from a result file is one of the detector's lidar boxes, to
    ``tol`` (m, rad)."""
    assert len(written) > 0
    dist = np.hypot(written[:, None, 0] - boxes[None, :, 0], written[:, None, 1] - boxes[None, :, 1])
    ref = boxes[dist.argmin(axis=1)]
    np.testing.assert_allclose(written[:, :6], ref[:, :6], atol=tol)
    np.testing.assert_allclose(_wrap(written[:, 6] - ref[:, 6]), 0, atol=tol)


def detector_boxes(perception, scan_path):
    scan = np.fromfile(scan_path, "<f4").reshape(-1, 4)
    det = perception.run(np.ascontiguousarray(scan[:, :3]), np.ascontiguousarray(scan[:, 3]))
    return det["detector"].boxes[det["detector"].keep]


def test_kitti_results_on_real_frames_read_back_to_the_detector_boxes(tmp_path):
    """``reference-perception kitti`` on real KITTI scans: lmd_ros reads the result files
    back, with the frame's calibration, to the detector's own lidar boxes. With the
    simulator's calibration in the writer (the old defect) boxes moved by up to 0.33 m."""
    from lidar_quality_training.lmd import dataset as D

    root = require_realdata_kitti()
    base = root / "training"
    out = tmp_path / "res"
    assert main(["kitti", "--root", str(root), "--out", str(out), "--heads", "0",
                 "--no-segmenter", "--quiet"]) == 0
    perception = Perception(detector=True, segmenter=False, heads=0)
    fids = sorted(p.stem for p in (base / "velodyne").glob("*.bin"))
    assert fids
    for fid in fids:
        boxes = detector_boxes(perception, base / "velodyne" / f"{fid}.bin")
        calib = D.read_calib(base / "calib" / f"{fid}.txt")
        written, _, _ = D.read_kitti_objects(out / f"{fid}.txt", calib, with_score=True)
        assert_written_boxes(written, boxes)
        # exactly the boxes in the frame's camera image, and the calibration recorded
        from lidar_sim import kitti
        assert len(written) == kitti.in_image(boxes, calib=calib).sum()
        assert (out / "calib" / f"{fid}.txt").read_text() == calib.text()


def test_kitti_dataset_without_calibration(sim_dir, tmp_path, capsys):
    """No calib file: the simulator's calibration, said and recorded; lmd_ros reads the
    results with the recorded one and refuses labels it cannot place."""
    from lidar_sim import kitti
    from lidar_quality_training.lmd import dataset as D

    root = tmp_path / "kitti"
    shutil.copytree(sim_dir / "kitti", root)
    shutil.rmtree(root / "training" / "calib")
    out = tmp_path / "res"
    assert main(["kitti", "--root", str(root), "--out", str(out), "--heads", "0",
                 "--no-segmenter", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and "calib/000000.txt missing" in err and "SIM_CALIB" in err
    fids = sorted(p.stem for p in out.glob("*.txt"))
    assert fids == ["000000", "000001"]
    assert all((out / "calib" / f"{f}.txt").read_text() == kitti.SIM_CALIB.text() for f in fids)
    with pytest.raises(FileNotFoundError, match=r"training/calib/000000.txt \(and 1 more frames\): "
                                                r"no calibration file"):
        D.load_kitti(root, out, [D.settings_for("none")], progress=False)
    # the dataset gets a calibration of its own that differs from the one the results were
    # written with: the results are still read with theirs
    other = kitti.Calibration(kitti.P2, kitti.R0_RECT,
                              kitti.TR_VELO_TO_CAM + [[0, 0, 0, 0.3], [0, 0, 0, 0], [0, 0, 0, 0]])
    (root / "training" / "calib").mkdir()
    for f in fids:
        kitti.calib_path(root / "training", f).write_text(other.text())
    ds = D.load_kitti(root, out, [D.settings_for("none")], progress=False)["none"]
    perception = Perception(detector=True, segmenter=False, heads=0)
    for k, f in enumerate(fids):
        boxes = detector_boxes(perception, root / "training" / "velodyne" / f"{f}.bin")
        assert_written_boxes(ds.box[ds.frame == k], boxes)


# ------------------------------------------------------------------ any bag
def users_bag(src, dst, *, break_cloud: int | None = None):
    """``src`` as a user's recording: the cloud on an Autoware topic, a driver's packet type
    unknown here beside it, older sqlite3 metadata; ``break_cloud``: that cloud truncated."""
    from lidar_quality_ros.bag_io import BagWriter
    from rclpy.serialization import deserialize_message, serialize_message
    from realbags import humble_metadata
    from sensor_msgs.msg import PointCloud2

    with BagWriter(dst, storage="sqlite3") as w:
        clouds = 0
        for m in read_bag(src):
            if m.topic != "/lidar/points":
                continue
            raw = m.raw
            if clouds == break_cloud:
                msg = deserialize_message(raw, PointCloud2)
                msg.data = bytes(msg.data)[:len(msg.data) - 5]
                raw = serialize_message(msg)
            clouds += 1
            w.write("/driver/packets", "velodyne_msgs/msg/VelodyneScan", m.stamp_ns - 1,
                    bytes([0, 1, 0, 0]) + bytes(100))
            w.write("/sensing/lidar/top/pointcloud", m.msgtype, m.stamp_ns, raw)
    humble_metadata(dst, storage_identifier="", serialization_format="")


def test_bag_topics_unknown_types_and_atomic_output(sim_dir, tmp_path, capsys):
    """--topic names the input cloud and outputs: the same outputs as under the default
    names; a packet type unknown here is copied unchanged with one warning; a run that
    fails midway (an unreadable cloud) leaves no output, the next needs no --overwrite."""
    src = sim_dir / "bags" / "seq_00"
    users = tmp_path / "users"
    users_bag(src, users)
    ref, out = tmp_path / "ref", tmp_path / "out"
    common = ["--quiet", "--heads", "1"]
    assert main(["bag", "--in", str(src), "--out", str(ref), *common]) == 0
    assert main(["bag", "--in", str(users), "--out", str(out), *common,
                 "--topic", "points=/sensing/lidar/top/pointcloud",
                 "--topic", "detections=/perception/object_recognition/objects",
                 "--topic", "head_0/variance=/ensemble/0/variance"]) == 0
    err = capsys.readouterr().err
    assert err.count("velodyne_msgs/msg/VelodyneScan") == 1 and "copied unchanged" in err
    topics = bag_topics(out)
    assert topics["/driver/packets"] == "velodyne_msgs/msg/VelodyneScan"
    assert [m.raw for m in read_bag(out, {"/driver/packets"})] == [
        m.raw for m in read_bag(users, {"/driver/packets"})]
    renamed = {"/perception/detections": "/perception/object_recognition/objects",
               "/perception/head_0/variance": "/ensemble/0/variance"}
    for t in ("/perception/detections", "/perception/proposals", "/perception/segmentation",
              "/perception/head_0", "/perception/head_0/variance"):
        new = renamed.get(t, t)
        assert new in topics and (t == new or t not in topics)
        a = [m.decode() for m in read_bag(ref, {t})]
        b = [m.decode() for m in read_bag(out, {new})]
        assert len(a) == 2 and a == b, t
    # a user's bag where the second cloud cannot be read: no output at all, said clearly
    broken = tmp_path / "broken"
    users_bag(src, broken, break_cloud=1)
    target = tmp_path / "target"
    argv = ["bag", "--in", str(broken), "--out", str(target), *common,
            "--topic", "points=/sensing/lidar/top/pointcloud"]
    with pytest.raises(SystemExit, match="cannot be read.*not written"):
        main(argv)
    assert not target.exists() and not list(tmp_path.glob(".target*"))
    argv[2] = str(users)
    assert main(argv) == 0 and bag_topics(target)["/perception/detections"]
    with pytest.raises(SystemExit) as e:      # a complete one: only with --overwrite
        main(argv)
    assert e.value.code == 2 and "--overwrite" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0
    with pytest.raises(SystemExit) as e:
        main(["bag", "--in", str(users), "--out", str(tmp_path / "x"), "--topic", "cloud=/a"])
    assert e.value.code == 2 and "unknown topic key 'cloud'" in capsys.readouterr().err
