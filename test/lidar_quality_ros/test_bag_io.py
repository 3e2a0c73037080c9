import numpy as np
import pytest
from lidar_quality_core.pointcloud import create_xyz_cloud, xyz_intensity
from lidar_quality_msgs.msg import BoxVariance, BoxVarianceArray
from rclpy.qos import HistoryPolicy, ReliabilityPolicy
from realbags import REAL_BAGS, humble_metadata, real_bag
from std_msgs.msg import Header
from vision_msgs.msg import Detection3D, Detection3DArray

from lidar_quality_ros.bag_io import (BagWriter, UnknownTypes, atomic_output, bag_info,
                                      bag_topics, known_type, message_class, partial_dirs,
                                      read_bag)


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


# --------------------------------------------------------------------------- any bag
def _small_bag(path, storage):
    h = Header(frame_id="lidar")
    with BagWriter(path, storage=storage) as w:
        for k in range(3):
            h.stamp.sec = k
            cloud = create_xyz_cloud(h, np.full((4, 3), k, np.float32))
            w.write("/pts", "sensor_msgs/msg/PointCloud2", 100 + k, cloud)
            w.write("/dets", "vision_msgs/msg/Detection3DArray", 100 + k,
                    Detection3DArray(header=h))
    return [(m.topic, m.stamp_ns, m.raw) for m in read_bag(path)]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("empty", ["storage_identifier", "serialization_format", "both", "none"])
def test_older_metadata_is_read(tmp_path, storage, empty):
    """Version 5 metadata with a QoS string, an empty storage identifier (inferred from the
    files) and / or an empty serialization format (CDR): read as rosbag2 reads it, the
    bag itself unchanged."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    bag = tmp_path / "b"
    before = _small_bag(bag, storage)
    ident = "" if empty in ("storage_identifier", "both") else storage
    fmt = "" if empty in ("serialization_format", "both") else "cdr"
    humble_metadata(bag, storage_identifier=ident, serialization_format=fmt,
                    db_format=fmt if storage == "sqlite3" else None)
    text = (bag / "metadata.yaml").read_text()
    if empty != "none":
        with pytest.raises(ReaderError), Reader(bag):    # what rosbags alone says
            pass
    info = bag_info(bag)
    assert sorted(info.fixes) == sorted(
        (["empty storage_identifier: " + storage + " (from the files)"] if not ident else [])
        + ([f"empty serialization_format of {t}: cdr" for t in ("/pts", "/dets")]
           if not fmt else []))
    assert {t: (i.msgtype, i.count) for t, i in info.topics.items()} == {
        "/pts": ("sensor_msgs/msg/PointCloud2", 3), "/dets": ("vision_msgs/msg/Detection3DArray", 3)}
    qos = info.topics["/pts"].qos[0]      # the recorded string, numeric policies
    assert (qos.depth, qos.reliability, qos.history) == (
        5, ReliabilityPolicy.BEST_EFFORT, HistoryPolicy.KEEP_LAST)
    assert (info.start_ns, info.end_ns) == (100, 102)
    assert [(m.topic, m.stamp_ns, m.raw) for m in read_bag(bag)] == before
    assert [m.stamp_ns for m in read_bag(bag, {"/dets"}, start_ns=101)] == [101, 102]
    assert bag_topics(bag) == {"/pts": "sensor_msgs/msg/PointCloud2",
                               "/dets": "vision_msgs/msg/Detection3DArray"}
    assert (bag / "metadata.yaml").read_text() == text       # never changed
    assert sorted(p.name for p in bag.iterdir()) == sorted(
        ["metadata.yaml", f"b.{'db3' if storage == 'sqlite3' else 'mcap'}"])


def test_unreadable_storage_identifier_is_a_clear_error(tmp_path):
    bag = tmp_path / "b"
    _small_bag(bag, "mcap")
    humble_metadata(bag)
    (bag / "b.mcap").rename(bag / "b.data")
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text().replace("b.mcap", "b.data"))
    with pytest.raises(ValueError, match="cannot tell sqlite3 from mcap"):
        bag_info(bag)


class _Log(list):
    def __call__(self, text):
        self.append(text)


def test_unknown_types_are_copied_raw_and_warned_once_per_type(tmp_path):
    """A driver's packet type (no rclpy class, not in our typestore): written and read as
    bytes, recorded without a definition; one warning per type, naming its topics."""
    raw = [bytes([0, 1, 0, 0]) + bytes(range(k, k + 40)) for k in range(3)]
    with BagWriter(tmp_path / "b") as w:
        for k, r in enumerate(raw):
            w.write("/velodyne_packets", "velodyne_msgs/msg/VelodyneScan", 10 + k, r)
            w.write("/rear/velodyne_packets", "velodyne_msgs/msg/VelodyneScan", 10 + k, r)
            w.write("/pandar_packets", "pandar_msgs/msg/PandarScan", 10 + k, r)
            w.write("/pts", "sensor_msgs/msg/PointCloud2", 10 + k,
                    create_xyz_cloud(Header(), np.zeros((2, 3), np.float32)))
    info = bag_info(tmp_path / "b")
    assert info.topics["/velodyne_packets"].msgtype == "velodyne_msgs/msg/VelodyneScan"
    assert info.topics["/velodyne_packets"].digest == ""
    assert [m.raw for m in read_bag(tmp_path / "b", {"/pandar_packets"})] == raw
    assert not known_type("velodyne_msgs/msg/VelodyneScan") and known_type(
        "sensor_msgs/msg/PointCloud2")
    log = _Log()
    unknown = UnknownTypes(log, "skipped")
    playable = unknown.check_all({t: i.msgtype for t, i in info.topics.items()})
    assert playable == ["/pts"]
    assert len(log) == 2 and "/velodyne_packets, /rear/velodyne_packets" in log[0]
    assert "pandar_msgs/msg/PandarScan" in log[1] and log[1].endswith("skipped")
    assert not unknown.check("/velodyne_packets", "velodyne_msgs/msg/VelodyneScan")
    assert not unknown.check("/third", "velodyne_msgs/msg/VelodyneScan")
    assert len(log) == 2                        # still one warning per type
    assert unknown.seen["velodyne_msgs/msg/VelodyneScan"][-1] == "/third"
    # copied again (as process_bag copies input topics), with the source's record
    with BagWriter(tmp_path / "c", storage="sqlite3") as w:
        for m in read_bag(tmp_path / "b"):
            w.write(m.topic, m.msgtype, m.stamp_ns, m.raw, source=info.topics[m.topic])
    assert [m.raw for m in read_bag(tmp_path / "c")] == [m.raw for m in read_bag(tmp_path / "b")]


def test_atomic_output(tmp_path):
    target = tmp_path / "out"
    with pytest.raises(RuntimeError, match="midway"):
        with atomic_output(target) as tmp:
            with BagWriter(tmp) as w:
                w.write("/a", "std_msgs/msg/Header", 1, Header())
                raise RuntimeError("midway")
    assert list(tmp_path.iterdir()) == []       # nothing at the target, nothing beside it
    with atomic_output(target) as tmp:
        with BagWriter(tmp) as w:
            w.write("/a", "std_msgs/msg/Header", 1, Header())
        assert not target.exists()
    assert bag_topics(target) == {"/a": "std_msgs/msg/Header"}
    assert (target / "out.mcap").exists() and list(tmp_path.iterdir()) == [target]
    with pytest.raises(FileExistsError):
        with atomic_output(target):
            pass
    with pytest.raises(KeyboardInterrupt):      # a failed replacement keeps the old one
        with atomic_output(target, overwrite=True) as tmp:
            tmp.mkdir()
            raise KeyboardInterrupt
    assert bag_topics(target) == {"/a": "std_msgs/msg/Header"}
    with atomic_output(target, overwrite=True) as tmp:
        with BagWriter(tmp) as w:
            w.write("/b", "std_msgs/msg/Header", 1, Header())
    assert bag_topics(target) == {"/b": "std_msgs/msg/Header"}
    assert list(tmp_path.iterdir()) == [target]
    # a killed run's leftover is hidden beside the target and removed by the next run
    (tmp_path / ".out.partial-x").mkdir()
    assert partial_dirs(target) == [tmp_path / ".out.partial-x"]
    with atomic_output(target, overwrite=True) as tmp:
        tmp.mkdir()
    assert list(tmp_path.iterdir()) == [target]


@pytest.mark.parametrize("name", sorted(REAL_BAGS))
def test_real_recordings_are_read(name):
    """The driver's genuine recordings (older metadata, unknown packet types)."""
    bag = real_bag(name)
    topic, msgtype, count, fixes = REAL_BAGS[name]
    info = bag_info(bag)
    assert info.fixes == fixes
    assert {t: (i.msgtype, i.count) for t, i in info.topics.items()} == {topic: (msgtype, count)}
    msgs = list(read_bag(bag))
    assert len(msgs) == count and all(len(m.raw) > 100_000 for m in msgs)
    assert [m.stamp_ns for m in msgs] == sorted(m.stamp_ns for m in msgs)
    assert (msgs[0].stamp_ns, msgs[-1].stamp_ns) == (info.start_ns, info.end_ns)


#: the quality arrays as version 0 defined them (before the version and drift fields)
VERSION_0 = {"DetectionQualityArray": "DetectionQuality[] detections",
             "SegmentQualityArray": "SegmentQuality[] segments",
             "ClusterUncertaintyArray": "ClusterUncertainty[] clusters"}


def version_0_typestore():
    """A typestore with the quality arrays of version 0 (their items are unchanged)."""
    from lidar_quality_core.rosbag_types import msg_dir
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for item in ("DetectionQuality", "SegmentQuality", "ClusterUncertainty"):
        text = (msg_dir("lidar_quality_msgs") / f"{item}.msg").read_text()
        types.update(get_types_from_msg(text, f"lidar_quality_msgs/msg/{item}"))
    for name, items in VERSION_0.items():
        text = ("std_msgs/Header header\nstring confidence_model_id\nstring iou_model_id\n"
                + items + "\n")
        types.update(get_types_from_msg(text, f"lidar_quality_msgs/msg/{name}"))
    store.register(types)
    return store


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_of_version_0_quality_messages_is_read_by_its_definition(tmp_path, storage):
    """A bag recorded before the drift fields: its bytes end where version 1's fields begin,
    so rclpy cannot read them with the installed definition; read_bag decodes them by the
    definition the bag recorded, the new fields at their defaults (version 0, drift level
    unknown), and BagWriter copies them with that definition."""
    from lidar_quality_msgs.msg import DetectionQualityArray
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    old = version_0_typestore()
    T = old.types
    name = "lidar_quality_msgs/msg/DetectionQualityArray"
    header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](7, 500), "lidar")
    items = [T["lidar_quality_msgs/msg/DetectionQuality"](i, f"d{i}", "car", 0.9, 0.25 * i,
                                                          0.5) for i in range(3)]
    raw = bytes(old.serialize_cdr(T[name](header, "clf-1", "reg-1", items), name))
    with pytest.raises(Exception, match="deserialize"):
        deserialize_message(raw, DetectionQualityArray)       # the installed definition
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    with Writer(tmp_path / "old", version=9, storage_plugin=plugin) as w:
        conn = w.add_connection("/lmd/output/quality", name, typestore=old)
        w.write(conn, 10, raw)

    def check(bag):
        (m,) = read_bag(bag)
        assert m.raw == raw and m.recorded      # the recorded (older) definition
        q = m.decode()
        assert isinstance(q, DetectionQualityArray)
        assert (q.header.stamp.sec, q.header.stamp.nanosec, q.header.frame_id) == (7, 500,
                                                                                   "lidar")
        assert (q.confidence_model_id, q.iou_model_id) == ("clf-1", "reg-1")
        assert [(d.detection_index, d.detection_id, d.confidence) for d in q.detections] == [
            (0, "d0", 0.0), (1, "d1", 0.25), (2, "d2", 0.5)]
        assert (q.version, q.drift_level) == (0, q.DRIFT_UNKNOWN)

    check(tmp_path / "old")
    info = bag_info(tmp_path / "old")
    t = info.topics["/lmd/output/quality"]
    with BagWriter(tmp_path / "copy") as w:       # copied bytes keep their definition
        w.write("/lmd/output/quality", name, 10, raw, source=t)
    check(tmp_path / "copy")
    assert bag_info(tmp_path / "copy").topics["/lmd/output/quality"].digest == t.digest
    # the installed definition's messages are decoded by rclpy as always
    new = DetectionQualityArray(header=Header(frame_id="lidar"), version=1, drift_level=3)
    with BagWriter(tmp_path / "new") as w:
        w.write("/q", name, 1, new)
    (m,) = read_bag(tmp_path / "new")
    assert not m.recorded and m.decode().drift_level == 3
