"""cloud_cdr: a PointCloud2 read from its CDR bytes equals rclpy's deserialization of them."""
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField

from lidar_quality_core.cloud_cdr import DecodedCloud, decode_point_cloud, serialized_cloud
from lidar_quality_core.detection_cdr import CdrError
from lidar_quality_core.pointcloud import cloud_to_structured, create_xyz_cloud


def _cloud(frame_id="lidar_top", fields=(("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)),
           height=1, width=5, point_step=12, row_pad=0, big=False, dense=True, seed=0):
    m = PointCloud2()
    m.header.frame_id = frame_id
    m.header.stamp.sec, m.header.stamp.nanosec = 1_700_000_000, 123_456_789
    m.height, m.width = height, width
    m.fields = [PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields]
    m.is_bigendian, m.point_step = big, point_step
    m.row_step = width * point_step + row_pad
    m.is_dense = dense
    rng = np.random.default_rng(seed)
    m.data = rng.integers(0, 256, height * m.row_step, dtype=np.uint8).tobytes()
    return m


def _same(d: DecodedCloud, m: PointCloud2):
    assert d.header == m.header
    assert (d.height, d.width, d.point_step, d.row_step) == (m.height, m.width, m.point_step,
                                                             m.row_step)
    assert d.is_bigendian == m.is_bigendian and d.is_dense == m.is_dense
    assert [(f.name, f.offset, f.datatype, f.count) for f in d.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in m.fields]
    assert d.data.dtype == np.uint8 and d.data.tobytes() == bytes(m.data)


CASES = {
    "xyz": {},
    # names of every length mod 4, counts > 1 and odd offsets: every alignment rule
    "odd fields": {"fields": (("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("ring", 12, 4, 1),
                              ("t", 14, 6, 1), ("probs", 18, 2, 20), ("flags_", 38, 1, 3)),
                   "point_step": 41, "width": 7},
    "organized with row padding": {"height": 3, "width": 4, "row_pad": 5},
    "big endian flag, not dense": {"big": True, "dense": False},
    "empty": {"width": 0},
    "no fields, empty frame id": {"fields": (), "frame_id": "", "point_step": 4},
    "utf-8 frame id": {"frame_id": "läser_ß"},
}


@pytest.mark.parametrize("kind", CASES)
def test_decoded_equals_rclpy(kind):
    m = _cloud(**CASES[kind])
    wire = serialize_message(m)
    d = decode_point_cloud(wire)
    _same(d, deserialize_message(wire, PointCloud2))
    assert d.data.base is wire  # a view of the received bytes, not a copy
    assert not d.data.flags.writeable


def test_pointcloud_reads_a_decoded_cloud_as_the_message():
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(300, 3)).astype(np.float32)
    msg = create_xyz_cloud(_cloud().header, xyz, rng.random(300).astype(np.float32),
                           ring=np.arange(300, dtype=np.uint16))
    wire = serialize_message(msg)
    a = cloud_to_structured(decode_point_cloud(wire))
    b = cloud_to_structured(deserialize_message(wire, PointCloud2))
    assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    # also from a bytearray / memoryview (a bag reader's buffer)
    _same(decode_point_cloud(memoryview(bytearray(wire))), msg)


def test_every_truncation_is_a_cdr_error():
    wire = serialize_message(_cloud(**CASES["odd fields"]))
    for n in range(len(wire)):
        with pytest.raises(CdrError):
            decode_point_cloud(wire[:n])


def test_other_encapsulations_and_lying_lengths_are_refused():
    wire = bytearray(serialize_message(_cloud()))
    with pytest.raises(CdrError, match="encapsulation 0000"):
        decode_point_cloud(b"\x00\x00" + bytes(wire[2:]))
    with pytest.raises(CdrError, match="encapsulation"):
        decode_point_cloud(b"")
    # the data length says more bytes than there are
    n_at = len(wire) - 1 - 5 * 12 - 4
    assert int.from_bytes(wire[n_at:n_at + 4], "little") == 60
    wire[n_at:n_at + 4] = (10**9).to_bytes(4, "little")
    with pytest.raises(CdrError, match="cannot fit"):
        decode_point_cloud(bytes(wire))


def test_random_corruption_gives_a_cloud_or_a_cdr_error():
    # what a fuzzer would send: flipped bytes anywhere; never any other exception
    wire = serialize_message(_cloud(**CASES["odd fields"]))
    rng = np.random.default_rng(7)
    outcomes = set()
    for _ in range(2000):
        b = bytearray(wire)
        for i in rng.integers(4, len(b), rng.integers(1, 4)):
            b[i] = rng.integers(0, 256)
        try:
            decode_point_cloud(bytes(b))
            outcomes.add("cloud")
        except CdrError:
            outcomes.add("error")
    assert outcomes == {"cloud", "error"}


@pytest.mark.parametrize("kind", [k for k in CASES if "row padding" not in k])
def test_serialized_cloud_is_rclpys_serialization(kind):
    # the message written by serialized_cloud, its data filled, against rclpy's bytes of
    # the same message (row_step is point_step * width there: no row padding); compared
    # as lengths and deserialized, since Fast CDR leaves its padding bytes undefined
    m = _cloud(**CASES[kind])
    fields = [(f.name, f.offset, f.datatype, f.count) for f in m.fields]
    wire, data = serialized_cloud(m.header, m.height, m.width, fields, m.is_bigendian,
                                  m.point_step)
    assert wire.dtype == np.uint8 and data.base is wire and data.flags.writeable  # a view
    assert len(data) == len(m.data)
    data[:] = np.frombuffer(bytes(m.data), np.uint8)
    wire[-1] = m.is_dense
    assert len(wire) == len(serialize_message(m))
    assert deserialize_message(wire.tobytes(), PointCloud2) == m
    _same(decode_point_cloud(wire.tobytes()), m)


def test_serialized_cloud_of_many_points_has_its_data_in_place():
    m = _cloud(width=100_000, fields=(("x", 0, 7, 1), ("label", 4, 4, 1)), point_step=6)
    wire, data = serialized_cloud(m.header, 1, m.width, [("x", 0, 7, 1), ("label", 4, 4, 1)],
                                  False, 6)
    data[:] = np.frombuffer(bytes(m.data), np.uint8)
    wire[-1] = 1
    assert len(wire) == len(serialize_message(m))
    assert deserialize_message(wire.tobytes(), PointCloud2) == m
