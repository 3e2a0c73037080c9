"""Tests of lidar_quality_core.pointcloud (PointCloud2 <-> numpy)."""
from __future__ import annotations

import array
import struct
from types import SimpleNamespace

import numpy as np
from lidar_quality_core.pcd import read_pcd
from realdata import REAL_FILES, realdata_dir
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from lidar_quality_core import pointcloud as pc
from lidar_quality_core.pointcloud import (
    CloudFormatError,
    cloud_dtype,
    cloud_to_structured,
    create_cloud,
    create_xyz_cloud,
    finite_mask,
    pointfield_datatype,
    read_fields,
    xyz_intensity,
)

# datatype code -> (numpy type char, struct format char), written out independently of the module.
CODES = {1: ("i1", "b"), 2: ("u1", "B"), 3: ("i2", "h"), 4: ("u2", "H"),
         5: ("i4", "i"), 6: ("u4", "I"), 7: ("f4", "f"), 8: ("f8", "d")}
# Unsigned integer of the same size: compares floats bit for bit (NaN payloads included).
UINT_OF_SIZE = {1: "u1", 2: "u2", 4: "u4", 8: "u8"}


def bits(a: np.ndarray) -> np.ndarray:
    """Native unsigned-integer image of an array's values (exact, NaN-safe comparison)."""
    a = np.asarray(a)
    a = a.astype(a.dtype.newbyteorder("="))
    return a.view(UINT_OF_SIZE[a.dtype.itemsize])


def random_values(rng, dt: np.dtype, shape) -> np.ndarray:
    """Values of dtype ``dt`` from random bytes (floats include NaN/inf/subnormals)."""
    n = int(np.prod(shape, dtype=np.int64))
    raw = rng.integers(0, 256, n * dt.itemsize, dtype=np.uint8)
    return raw.view(dt.newbyteorder("=")).reshape(shape).astype(dt)


def pf(name, offset, datatype, count=1):
    return PointField(name=name, offset=offset, datatype=datatype, count=count)


def make_msg(fields, data, *, height=1, width=None, point_step, row_step=None, big=False):
    msg = PointCloud2()
    msg.fields = list(fields)
    msg.point_step = point_step
    msg.height = height
    msg.width = width
    msg.row_step = point_step * width if row_step is None else row_step
    msg.is_bigendian = big
    msg.data = data
    return msg


def duck_msg(data, **kw):
    """Message-like object keeping ``data`` as is (the generated setter would convert it)."""
    msg = make_msg(kw.pop("fields"), b"", **kw)
    return SimpleNamespace(height=msg.height, width=msg.width, point_step=msg.point_step,
                           row_step=msg.row_step, is_bigendian=msg.is_bigendian,
                           fields=msg.fields, data=data)


def assert_fields_equal(decoded: np.ndarray, expected: np.ndarray, names=None):
    for name in names or expected.dtype.names:
        assert decoded[name].shape == expected[name].shape, name
        np.testing.assert_array_equal(bits(decoded[name]), bits(expected[name]), err_msg=name)


# --------------------------------------------------------------------------- datatypes

@pytest.mark.parametrize("code", sorted(CODES))
@pytest.mark.parametrize("count", [1, 3])
def test_round_trip_each_datatype(code, count):
    rng = np.random.default_rng(code * 10 + count)
    dt = np.dtype(CODES[code][0])
    n = 37
    vals = random_values(rng, dt, (n, count) if count > 1 else (n,))
    x = random_values(rng, np.dtype("f4"), (n,))
    msg = create_cloud(Header(frame_id="f"), {"x": x, "v": vals})
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("v", 4, code, count)]
    assert msg.point_step == 4 + dt.itemsize * count
    assert msg.row_step == msg.point_step * n and (msg.height, msg.width) == (1, n)
    assert len(msg.data) == msg.row_step
    assert msg.header.frame_id == "f"
    s = cloud_to_structured(msg)
    assert s.shape == (n,) and s.dtype.itemsize == msg.point_step
    assert s.dtype["v"].base.kind == dt.kind and s.dtype["v"].base.itemsize == dt.itemsize
    np.testing.assert_array_equal(bits(s["v"]), bits(vals))
    np.testing.assert_array_equal(bits(s["x"]), bits(x))
    # Independent check of the wire bytes of the last point.
    last = bytes(msg.data[-msg.point_step:])
    fmt = "<" + "f" + CODES[code][1] * count
    expect = struct.pack("<f", x[-1]) + vals[-1].astype(dt.newbyteorder("<")).tobytes()
    assert last == expect and struct.calcsize(fmt) == msg.point_step
    if code != 8 and code != 6:  # float64/uint32 -> float32 is lossy; compare exactly elsewhere
        got = read_fields(msg, ["v"], dtype=np.float64)
        np.testing.assert_array_equal(got, vals.reshape(n, count).astype(np.float64))


def test_pointfield_datatype_mapping():
    for code, (char, _) in CODES.items():
        assert pointfield_datatype(char) == code
        assert pointfield_datatype(np.dtype(char).newbyteorder(">")) == code
    assert pointfield_datatype(np.bool_) == pc.UINT8
    for bad in (np.int64, np.uint64, np.float16, np.complex64, "U3", object, "V4"):
        with pytest.raises(CloudFormatError, match="no PointField datatype"):
            pointfield_datatype(bad)
    with pytest.raises(CloudFormatError):
        pointfield_datatype(np.dtype([("a", "f4")]))


def test_bool_column_is_uint8():
    flags = np.array([True, False, True])
    msg = create_cloud(None, {"x": np.zeros(3, np.float32), "valid": flags})
    assert msg.fields[1].datatype == pc.UINT8
    np.testing.assert_array_equal(cloud_to_structured(msg)["valid"], [1, 0, 1])


def test_int64_column_rejected():
    with pytest.raises(CloudFormatError, match="int64"):
        create_cloud(None, {"x": np.arange(3)})


# --------------------------------------------------------------------------- layout

def test_cloud_dtype_offsets_padding_and_count():
    fields = [pf("x", 0, 7), pf("ring", 6, 4), pf("rgb", 8, 2, 3), pf("gone", 11, 7, 0),
              pf("t", 16, 8)]
    dt = cloud_dtype(fields, 32, False)
    assert dt.itemsize == 32
    assert dt.names == ("x", "ring", "rgb", "t")
    assert dt.fields["ring"] == (np.dtype("<u2"), 6)
    assert dt.fields["rgb"][0].shape == (3,) and dt.fields["rgb"][1] == 8
    assert dt.fields["t"] == (np.dtype("<f8"), 16)
    big = cloud_dtype(fields, 32, True)
    assert big.fields["t"][0] == np.dtype(">f8") and big.fields["ring"][0] == np.dtype(">u2")


def test_hand_built_padded_layout_decodes():
    rng = np.random.default_rng(1)
    # Gaps before "ring", between "rgb" and "t", and 5 trailing bytes.
    layout = np.dtype({"names": ["x", "ring", "rgb", "t"],
                       "formats": ["<f4", "<u2", ("u1", (3,)), "<f8"],
                       "offsets": [0, 6, 8, 16], "itemsize": 29})
    n = 50
    raw = rng.integers(0, 256, n * 29, dtype=np.uint8)
    ref = raw.view(layout)
    fields = [pf("x", 0, 7), pf("ring", 6, 4), pf("rgb", 8, 2, 3), pf("t", 16, 8),
              pf("empty", 24, 7, 0)]
    msg = make_msg(fields, raw.tobytes(), width=n, point_step=29)
    s = cloud_to_structured(msg)
    assert s.dtype.names == ("x", "ring", "rgb", "t")
    assert_fields_equal(s, ref)
    cols = read_fields(msg, ["ring", "rgb"], dtype=np.int32)
    assert cols.shape == (n, 4) and cols.flags.c_contiguous
    np.testing.assert_array_equal(cols[:, 0], ref["ring"])
    np.testing.assert_array_equal(cols[:, 1:], ref["rgb"])


def test_organized_cloud_round_trip():
    rng = np.random.default_rng(2)
    h, w = 4, 9
    arr = np.zeros((h, w), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2")])
    for name in arr.dtype.names:
        arr[name] = random_values(rng, arr.dtype[name], (h, w))
    msg = create_cloud(None, arr)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (h, w, 14, 14 * w)
    s = cloud_to_structured(msg)
    assert s.shape == (h, w)
    assert_fields_equal(s, arr)
    got = read_fields(msg, ["x", "ring"])
    assert got.shape == (h * w, 2)
    np.testing.assert_array_equal(bits(got[:, 0]), bits(arr["x"].reshape(-1)))
    np.testing.assert_array_equal(got[:, 1], arr["ring"].reshape(-1).astype(np.float32))


@pytest.mark.parametrize("last_row_padded", [True, False])
def test_row_padding_strided_view(last_row_padded):
    rng = np.random.default_rng(3)
    h, w, ps, rs = 3, 5, 8, 8 * 5 + 12
    layout = np.dtype({"names": ["x", "i"], "formats": ["<f4", "<u2"],
                       "offsets": [0, 4], "itemsize": ps})
    rows = rng.integers(0, 256, (h, rs), dtype=np.uint8)
    ref = rows[:, : w * ps].copy().view(layout)  # (h, w)
    raw = rows.tobytes()
    if not last_row_padded:
        raw = raw[: rs * (h - 1) + w * ps]
    msg = make_msg([pf("x", 0, 7), pf("i", 4, 4)], raw, height=h, width=w,
                   point_step=ps, row_step=rs)
    s = cloud_to_structured(msg)
    assert s.shape == (h, w) and s.strides == (rs, ps)
    assert_fields_equal(s, ref)
    assert np.shares_memory(s, np.frombuffer(msg.data, np.uint8))
    xyz = read_fields(msg, ["x", "i"], dtype=np.float64)
    np.testing.assert_array_equal(xyz[:, 1], ref["i"].reshape(-1))


def test_single_row_with_row_padding():
    layout = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    ref = np.arange(12, dtype=np.float32).view(layout)
    msg = make_msg([pf("x", 0, 7), pf("y", 4, 7), pf("z", 8, 7)], ref.tobytes() + bytes(4),
                   width=4, point_step=12, row_step=52)
    xyz, inten = xyz_intensity(msg)
    np.testing.assert_array_equal(xyz, np.arange(12, dtype=np.float32).reshape(4, 3))
    assert inten is None


def test_big_endian_structured_round_trip():
    rng = np.random.default_rng(4)
    big = np.dtype([("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("intensity", ">u2"),
                    ("t", ">f8"), ("flag", "u1"), ("v", ">i4", (2,))])
    arr = np.zeros(21, big)
    for name in big.names:
        arr[name] = random_values(rng, big[name].base, arr[name].shape)
    msg = create_cloud(None, arr)
    assert msg.is_bigendian is True
    assert bytes(msg.data) == arr.tobytes()  # already packed: wire bytes are the array bytes
    assert bytes(msg.data[:4]) == struct.pack(">f", float(arr["x"][0])) or np.isnan(arr["x"][0])
    s = cloud_to_structured(msg)
    assert s.dtype["t"] == np.dtype(">f8") and s.dtype["intensity"] == np.dtype(">u2")
    assert_fields_equal(s, arr)
    xyz, inten = xyz_intensity(msg)
    assert xyz.dtype == np.float32 and xyz.dtype.isnative
    np.testing.assert_array_equal(bits(xyz[:, 1]), bits(arr["y"]))
    np.testing.assert_array_equal(inten, arr["intensity"].astype(np.float32))


def test_big_endian_hand_built_against_struct():
    vals = [(1.5, 513), (-2.25, 65534), (float("nan"), 7)]
    raw = b"".join(struct.pack(">fxxH", x, i) for x, i in vals)
    msg = make_msg([pf("x", 0, 7), pf("i", 6, 4)], raw, width=3, point_step=8, big=True)
    s = cloud_to_structured(msg)
    np.testing.assert_array_equal(s["i"], [513, 65534, 7])
    np.testing.assert_array_equal(s["x"], np.array([1.5, -2.25, np.nan], np.float32))
    # The same bytes read little-endian give different numbers.
    msg.is_bigendian = False
    assert cloud_to_structured(msg)["i"][0] == 258


def test_mixed_byte_order_becomes_native():
    arr = np.zeros(3, [("x", ">f4"), ("i", "<u2")])
    arr["x"] = [1, 2, 3]
    arr["i"] = [4, 5, 6]
    msg = create_cloud(None, arr)
    assert msg.is_bigendian is False
    s = cloud_to_structured(msg)
    np.testing.assert_array_equal(s["x"], [1, 2, 3])
    np.testing.assert_array_equal(s["i"], [4, 5, 6])


def test_non_contiguous_and_padded_structured_input_is_packed():
    padded = np.dtype({"names": ["x", "y", "z"], "formats": ["f4"] * 3,
                       "offsets": [0, 4, 8], "itemsize": 32})
    arr = np.zeros(10, padded)
    arr["x"] = np.arange(10)
    arr["z"] = -np.arange(10)
    for src in (arr, arr[::3], arr[["z", "x"]]):
        msg = create_cloud(None, src)
        assert msg.point_step == 4 * len(src.dtype.names)
        assert [f.name for f in msg.fields] == list(src.dtype.names)
        assert_fields_equal(cloud_to_structured(msg), src)


def test_dict_columns_with_count():
    rng = np.random.default_rng(5)
    xyz = rng.random((6, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (6, 3)).astype(np.uint8)
    msg = create_cloud(None, {"xyz": xyz, "rgb": rgb, "t": np.arange(6, dtype=np.float64)})
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("xyz", 0, 7, 3), ("rgb", 12, 2, 3), ("t", 15, 8, 1)]
    assert msg.point_step == 23
    s = cloud_to_structured(msg)
    np.testing.assert_array_equal(s["xyz"], xyz)
    np.testing.assert_array_equal(s["rgb"], rgb)
    np.testing.assert_array_equal(read_fields(msg, ["t", "xyz"])[:, 1:], xyz)


def test_create_xyz_cloud_and_extras():
    xyz = np.arange(15, dtype=np.float64).reshape(5, 3)
    msg = create_xyz_cloud(None, xyz, intensity=[1, 2, 3, 4, 5],
                           ring=np.arange(5, dtype=np.uint16))
    assert [(f.name, f.datatype) for f in msg.fields] == [
        ("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("ring", 4)]
    got_xyz, inten = xyz_intensity(msg)
    np.testing.assert_array_equal(got_xyz, xyz.astype(np.float32))
    np.testing.assert_array_equal(inten, [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(cloud_to_structured(msg)["ring"], np.arange(5))
    assert xyz_intensity(create_xyz_cloud(None, xyz))[1] is None


@pytest.mark.parametrize("code", [1, 2, 3, 4, 5, 6])
def test_integer_coordinates_are_refused(code):
    """x, y, z as integers (mm / cm in the drivers that do it) were read as metres."""
    np_type = np.dtype(CODES[code][0])
    cols = {"x": np.zeros(3, np.float32), "y": np.arange(3).astype(np_type),
            "z": np.zeros(3, np.float32), "intensity": np.ones(3, np.uint8)}
    msg = create_cloud(None, cols)
    name = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32"}[code]
    with pytest.raises(CloudFormatError, match=f"cloud field 'y' is {name}: x, y, z must be "
                                               "FLOAT32 / FLOAT64 metres"):
        xyz_intensity(msg)
    from lidar_quality_core.pointcloud import check_xyz_fields

    with pytest.raises(CloudFormatError, match=f"input/points field 'y' is {name}"):
        check_xyz_fields(cloud_to_structured(msg).dtype, "input/points")
    cols["y"] = cols["y"].astype(np.float64)  # float64 is fine (read as float32)
    np.testing.assert_array_equal(xyz_intensity(create_cloud(None, cols))[0][:, 1], [0, 1, 2])


def test_intensity_name_fallbacks():
    cols = {"x": np.zeros(2, np.float32), "y": np.zeros(2, np.float32),
            "z": np.zeros(2, np.float32), "reflectance": np.array([3, 4], np.uint8)}
    _, inten = xyz_intensity(create_cloud(None, cols))
    np.testing.assert_array_equal(inten, [3, 4])
    assert inten.dtype == np.float32
    cols["i"] = np.array([7.0, 8.0], np.float32)
    _, inten = xyz_intensity(create_cloud(None, cols), intensity_names=("i", "reflectance"))
    np.testing.assert_array_equal(inten, [7, 8])


# --------------------------------------------------------------------------- dense / finite

def test_is_dense_and_finite_mask():
    xyz = np.ones((5, 3), np.float32)
    assert create_xyz_cloud(None, xyz).is_dense is True
    xyz[2, 1] = np.nan
    xyz[4, 0] = np.inf
    msg = create_xyz_cloud(None, xyz)
    assert msg.is_dense is False
    np.testing.assert_array_equal(finite_mask(xyz_intensity(msg)[0]),
                                  [True, True, False, True, False])
    # A NaN outside x/y/z does not make the cloud sparse.
    ok = create_xyz_cloud(None, np.ones((2, 3)), intensity=[np.nan, 1])
    assert ok.is_dense is True
    organized = np.zeros((2, 2), [("x", "f4"), ("y", "f4"), ("z", "f4")])
    organized["z"][1, 1] = np.nan
    assert create_cloud(None, organized).is_dense is False


def test_finite_mask_matches_reference():
    rng = np.random.default_rng(6)
    a = rng.random((200, 3))
    a[rng.random((200, 3)) < 0.1] = np.nan
    a[rng.random((200, 3)) < 0.05] = -np.inf
    np.testing.assert_array_equal(finite_mask(a), np.isfinite(a).all(axis=1))
    np.testing.assert_array_equal(finite_mask(a.reshape(10, 20, 3)),
                                  np.isfinite(a).all(axis=1).reshape(10, 20))
    with pytest.raises(ValueError):
        finite_mask(np.zeros((3, 0)))


# --------------------------------------------------------------------------- empty clouds

def test_empty_clouds():
    msg = create_cloud(None, {"x": np.zeros(0, np.float32), "i": np.zeros(0, np.uint16)})
    assert (msg.height, msg.width, msg.point_step, msg.row_step, len(msg.data)) == (1, 0, 6, 0, 0)
    s = cloud_to_structured(msg)
    assert s.shape == (0,) and s.dtype.names == ("x", "i") and s.dtype.itemsize == 6
    assert read_fields(msg, ["x", "i"]).shape == (0, 2)
    empty_struct = np.zeros((0,), [("x", "f4"), ("y", "f4"), ("z", "f4")])
    xyz, inten = xyz_intensity(create_cloud(None, empty_struct))
    assert xyz.shape == (0, 3) and inten is None
    default = PointCloud2()
    assert cloud_to_structured(default).shape == (0,)
    # Empty message with fields but point_step left at 0: dtype sized from the fields.
    lazy = make_msg([pf("x", 0, 7), pf("y", 4, 7)], b"", width=0, point_step=0)
    assert cloud_to_structured(lazy).dtype.names == ("x", "y")
    organized_empty = np.zeros((3, 0), [("x", "f4")])
    m2 = create_cloud(None, organized_empty)
    assert (m2.height, m2.width) == (3, 0)
    assert cloud_to_structured(m2).shape == (3, 0)


# ------------------------------------------------------------------ zero copy / data types

def test_zero_copy_view_shares_message_buffer():
    msg = create_xyz_cloud(None, np.arange(30, dtype=np.float32).reshape(10, 3))
    assert type(msg.data) is array.array and msg.data.typecode == "B"
    s = cloud_to_structured(msg)
    assert np.shares_memory(s, np.frombuffer(msg.data, np.uint8))
    s["y"][3] = 123.0  # writes through to the message
    assert struct.unpack_from("<f", msg.data, 3 * 12 + 4)[0] == 123.0
    # While the view lives the array.array may not be resized; afterwards it may.
    with pytest.raises(BufferError):
        msg.data.append(0)
    del s
    msg.data.append(0)


def test_build_leaves_no_buffer_export():
    msg = create_xyz_cloud(None, np.zeros((4, 3)))
    msg.data.extend([0])  # raises BufferError if create_cloud kept a view alive
    arr = np.zeros(4, [("x", "f4"), ("y", "f4"), ("z", "f4")])
    create_cloud(None, arr).data.extend([0])


def test_create_cloud_passes_check_fields(monkeypatch):
    """Message built with type checking on: every field value has the exact ROS Python type."""
    import sensor_msgs.msg._point_cloud2 as gen_cloud
    import sensor_msgs.msg._point_field as gen_field

    monkeypatch.setattr(gen_cloud, "ros_python_check_fields", "1")
    monkeypatch.setattr(gen_field, "ros_python_check_fields", "1")
    arr = np.zeros((2, 3), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("rgb", "u1", (3,))])
    arr["x"] = np.arange(6).reshape(2, 3)
    for fields in (arr, {"x": np.arange(3, dtype=np.float32), "c": np.ones((3, 2), np.uint16)}):
        msg = create_cloud(None, fields)
        assert msg._check_fields
        assert type(msg.data) is array.array and msg.data.typecode == "B"
        for key in ("height", "width", "point_step", "row_step"):
            assert type(getattr(msg, key)) is int, key
        assert all(type(f.offset) is int and type(f.count) is int for f in msg.fields)
    np.testing.assert_array_equal(cloud_to_structured(create_cloud(None, arr))["x"], arr["x"])


def test_rclpy_serialization_round_trip():
    """What a publisher sends and a subscriber receives decodes identically (and zero-copy)."""
    serialization = pytest.importorskip("rclpy.serialization")
    rng = np.random.default_rng(7)
    xyz = rng.random((1000, 3)).astype(np.float32)
    xyz[::7, 2] = np.nan
    msg = create_xyz_cloud(Header(frame_id="lidar"), xyz, intensity=rng.random(1000),
                           ring=(np.arange(1000) % 32).astype(np.uint16))
    wire = serialization.serialize_message(msg)
    got = serialization.deserialize_message(wire, PointCloud2)
    assert type(got.data) is array.array and bytes(got.data) == bytes(msg.data)
    assert got.header.frame_id == "lidar" and got.is_dense is False
    s = cloud_to_structured(got)
    assert np.shares_memory(s, np.frombuffer(got.data, np.uint8))
    np.testing.assert_array_equal(bits(xyz_intensity(got)[0]), bits(xyz))
    np.testing.assert_array_equal(s["ring"], np.arange(1000) % 32)


def _xyz_bytes():
    ref = np.arange(12, dtype="<f4")
    return ref, ref.tobytes()


@pytest.mark.parametrize("kind", ["bytes", "bytearray", "array", "list", "ndarray", "memoryview"])
def test_message_setter_data_types(kind):
    """Whatever is assigned, Jazzy's setter stores an array.array('B'); decoding works."""
    ref, raw = _xyz_bytes()
    value = {"bytes": raw, "bytearray": bytearray(raw), "array": array.array("B", raw),
             "list": list(raw), "ndarray": np.frombuffer(raw, np.uint8).copy(),
             "memoryview": memoryview(raw)}[kind]
    fields = [pf("x", 0, 7), pf("y", 4, 7), pf("z", 8, 7)]
    if kind == "ndarray" and PointCloud2()._check_fields:
        # With ROS_PYTHON_CHECK_FIELDS=1 the setter insists on Python ints.
        with pytest.raises(AssertionError):
            make_msg(fields, value, width=4, point_step=12)
        return
    msg = make_msg(fields, value, width=4, point_step=12)
    assert type(msg.data) is array.array
    np.testing.assert_array_equal(xyz_intensity(msg)[0], ref.reshape(4, 3))


@pytest.mark.parametrize("kind", ["bytes", "bytearray", "array", "ndarray", "ndarray_2d",
                                  "memoryview", "list", "tuple", "ndarray_int64",
                                  "strided_ndarray", "int8"])
def test_raw_data_objects(kind):
    """Duck-typed messages keep data as given: buffers are viewed, sequences copied."""
    ref, raw = _xyz_bytes()
    u8 = np.frombuffer(raw, np.uint8).copy()
    value = {"bytes": raw, "bytearray": bytearray(raw), "array": array.array("B", raw),
             "ndarray": u8, "ndarray_2d": u8.reshape(4, 12), "memoryview": memoryview(u8),
             "list": list(raw), "tuple": tuple(raw), "ndarray_int64": u8.astype(np.int64),
             "strided_ndarray": np.repeat(u8, 2)[::2], "int8": u8.view(np.int8)}[kind]
    msg = duck_msg(value, fields=[pf("x", 0, 7), pf("y", 4, 7), pf("z", 8, 7)],
                   width=4, point_step=12)
    s = cloud_to_structured(msg)
    np.testing.assert_array_equal(s["z"], ref[2::3])
    if kind in ("bytes", "bytearray", "array", "ndarray", "ndarray_2d", "memoryview", "int8"):
        backing = value if isinstance(value, np.ndarray) else np.frombuffer(value, np.uint8)
        assert np.shares_memory(s, backing)


def test_bad_data_values():
    fields = [pf("x", 0, 7)]
    with pytest.raises(CloudFormatError, match="outside 0..255"):
        cloud_to_structured(duck_msg([0, 1, 2, 300], fields=fields, width=1, point_step=4))
    with pytest.raises(CloudFormatError, match="byte values"):
        cloud_to_structured(duck_msg(np.zeros(4), fields=fields, width=1, point_step=4))
    with pytest.raises(CloudFormatError, match="cannot read PointCloud2 data of type list"):
        cloud_to_structured(duck_msg([object()] * 4, fields=fields, width=1, point_step=4))
    with pytest.raises(CloudFormatError, match="cannot read PointCloud2 data of type dict"):
        cloud_to_structured(duck_msg({1: 2}, fields=fields, width=1, point_step=4))


# --------------------------------------------------------------------------- error paths

def test_error_unknown_datatype():
    for code in (0, 9):
        with pytest.raises(CloudFormatError,
                           match=rf"field 'bad' has unknown PointField datatype {code}"):
            cloud_dtype([pf("x", 0, 7), pf("bad", 4, code)], 8)


def test_error_field_past_point_step():
    with pytest.raises(CloudFormatError,
                       match=r"'rgb' \(UINT8 x 3 at offset 6\) ends at byte 9, past point_step 8"):
        cloud_dtype([pf("x", 0, 7), pf("rgb", 6, 2, 3)], 8)
    msg = make_msg([pf("x", 0, 8)], bytes(8), width=2, point_step=4)
    with pytest.raises(CloudFormatError, match="past point_step 4"):
        cloud_to_structured(msg)


def test_error_overlapping_fields():
    with pytest.raises(CloudFormatError,
                       match=r"'x' \(bytes 0..4\) and 'y' \(bytes 2..6\) overlap"):
        cloud_dtype([pf("y", 2, 7), pf("x", 0, 7)], 8)
    with pytest.raises(CloudFormatError, match="overlap"):
        cloud_dtype([pf("v", 0, 4, 3), pf("w", 4, 2)], 8)
    cloud_dtype([pf("v", 0, 4, 2), pf("w", 4, 2)], 8)  # touching is fine


def test_error_duplicate_names():
    with pytest.raises(CloudFormatError, match="duplicate field name 'x'"):
        cloud_dtype([pf("x", 0, 7), pf("x", 4, 7)], 8)


def test_error_point_step_zero_with_points():
    msg = make_msg([], b"", width=3, point_step=0, row_step=0)
    with pytest.raises(CloudFormatError, match=r"point_step is 0 but the cloud has 3 points"):
        cloud_to_structured(msg)


def test_error_truncated():
    msg = make_msg([pf("x", 0, 7)], bytes(10), width=3, point_step=4)
    with pytest.raises(CloudFormatError, match=r"truncated data: 10 bytes, need 12"):
        cloud_to_structured(msg)
    # Rows padded to 20 bytes: 2 rows need 20 + 12 = 32 bytes.
    msg = make_msg([pf("x", 0, 7)], bytes(31), height=2, width=3, point_step=4, row_step=20)
    with pytest.raises(CloudFormatError, match=r"31 bytes, need 32 .*row_step 20"):
        cloud_to_structured(msg)


def test_error_row_step_too_small():
    msg = make_msg([pf("x", 0, 7)], bytes(20), height=2, width=3, point_step=4, row_step=10)
    with pytest.raises(CloudFormatError, match=r"row_step 10 < width 3 x point_step 4 = 12"):
        cloud_to_structured(msg)


def test_error_inconsistent_sizes():
    msg = make_msg([pf("x", 0, 7)], bytes(16), width=3, point_step=4)
    with pytest.raises(CloudFormatError,
                       match=r"data holds 16 bytes but height 1 x row_step 12 = 12"):
        cloud_to_structured(msg)
    msg = make_msg([pf("x", 0, 7)], bytes(4), width=0, point_step=4)
    with pytest.raises(CloudFormatError, match="data holds 4 bytes but height 1 x row_step 0 = 0"):
        cloud_to_structured(msg)


def test_error_missing_field_names_available():
    msg = create_xyz_cloud(None, np.zeros((2, 3)))
    with pytest.raises(CloudFormatError,
                       match=r"field 'ring' not in cloud; available fields: x, y, z"):
        read_fields(msg, ["x", "ring"])
    only_xy = create_cloud(None, {"x": np.zeros(2, np.float32), "y": np.zeros(2, np.float32)})
    with pytest.raises(CloudFormatError, match=r"field 'z' not in cloud; available fields: x, y"):
        xyz_intensity(only_xy)


def test_error_xyz_with_count():
    msg = create_cloud(None, {"x": np.zeros((2, 2), np.float32), "y": np.zeros(2, np.float32),
                              "z": np.zeros(2, np.float32)})
    with pytest.raises(CloudFormatError, match="'x' has count 2, expected 1"):
        xyz_intensity(msg)


def test_error_bad_build_inputs():
    with pytest.raises(CloudFormatError, match="structured array or a dict"):
        create_cloud(None, np.zeros((3, 3), np.float32))
    with pytest.raises(CloudFormatError, match="structured array or a dict"):
        create_cloud(None, [1, 2, 3])
    with pytest.raises(CloudFormatError, match=r"column 'y' has 2 rows, expected 3"):
        create_cloud(None, {"x": np.zeros(3, np.float32), "y": np.zeros(2, np.float32)})
    with pytest.raises(CloudFormatError, match=r"must be \(N,\) or \(H, W\)"):
        create_cloud(None, np.zeros((2, 2, 2), [("x", "f4")]))
    with pytest.raises(CloudFormatError, match=r"sub-array shape \(2, 2\)"):
        create_cloud(None, np.zeros(2, [("m", "f4", (2, 2))]))
    with pytest.raises(CloudFormatError, match=r"xyz must have shape \(N, 3\)"):
        create_xyz_cloud(None, np.zeros((4, 2)))
    with pytest.raises(CloudFormatError, match="duplicates"):
        create_xyz_cloud(None, np.zeros((4, 3)), x=np.zeros(4))
    with pytest.raises(CloudFormatError, match="without fields"):
        create_cloud(None, np.zeros(3, np.dtype([])))
    with pytest.raises(CloudFormatError, match=r"column 'c' must be"):
        create_cloud(None, {"c": np.zeros((3, 2, 2), np.float32)})


def test_errors_are_value_errors():
    assert issubclass(CloudFormatError, ValueError)


# --------------------------------------------------------------------------- property tests

@st.composite
def layouts(draw):
    """Random PointField layout with gaps, counts (0..3), trailing and row padding."""
    n_fields = draw(st.integers(1, 6))
    fields, offset = [], draw(st.integers(0, 3))
    for k in range(n_fields):
        code = draw(st.sampled_from(sorted(CODES)))
        count = draw(st.integers(0, 3))
        fields.append((f"f{k}", offset, code, count))
        offset += np.dtype(CODES[code][0]).itemsize * count + draw(st.integers(0, 5))
    order = draw(st.permutations(range(n_fields)))  # PointField order need not follow offsets
    point_step = offset + draw(st.integers(0, 4))
    height = draw(st.integers(1, 4))
    width = draw(st.integers(0, 6))
    row_pad = draw(st.integers(0, 7)) if height > 1 else 0
    return ([fields[i] for i in order], max(point_step, 1), height, width, row_pad,
            draw(st.booleans()), draw(st.booleans()))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(layout=layouts(), seed=st.integers(0, 2**32 - 1))
def test_property_decode_matches_struct(layout, seed):
    """Decoding random bytes agrees bit for bit with struct.unpack_from at every offset."""
    fields, ps, h, w, row_pad, big, trim_last = layout
    rs = w * ps + row_pad
    nbytes = rs * h - (row_pad if trim_last else 0)
    raw = np.random.default_rng(seed).integers(0, 256, nbytes, dtype=np.uint8).tobytes()
    msg = make_msg([pf(*f) for f in fields], raw, height=h, width=w, point_step=ps,
                   row_step=rs, big=big)
    s = cloud_to_structured(msg)
    assert s.shape == ((h, w) if h > 1 else (w,))
    assert set(s.dtype.names) == {f[0] for f in fields if f[3] > 0}
    s2 = s.reshape(h, w)
    e = ">" if big else "<"
    for name, offset, code, count in fields:
        if count == 0:
            continue
        size = np.dtype(CODES[code][0]).itemsize
        ufmt = e + {1: "B", 2: "H", 4: "I", 8: "Q"}[size]
        expect = np.array(
            [[[struct.unpack_from(ufmt, raw, r * rs + c * ps + offset + k * size)[0]
               for k in range(count)] for c in range(w)] for r in range(h)],
            dtype=np.uint64).reshape(h, w, count)
        got = bits(s2[name]).astype(np.uint64).reshape(h, w, count)
        np.testing.assert_array_equal(got, expect, err_msg=name)


@settings(max_examples=100, deadline=None)
@given(layout=layouts(), seed=st.integers(0, 2**32 - 1))
def test_property_build_decode_round_trip(layout, seed):
    """Random columns (count, dtype, byte order, NaN bit patterns) survive create_cloud."""
    fields, _, h, w, _, big, organized = layout
    rng = np.random.default_rng(seed)
    e = ">" if big else "<"
    specs = [(name, np.dtype(CODES[code][0]).newbyteorder(e), count)
             for name, _, code, count in fields if count > 0]
    if not specs:
        return
    shape = (h, w) if organized else (h * w,)
    arr = np.zeros(shape, [(n, dt) if c == 1 else (n, dt, (c,)) for n, dt, c in specs])
    for name, dt, c in specs:
        arr[name] = random_values(rng, dt, arr[name].shape)
    msg = create_cloud(None, arr)
    multibyte = any(dt.itemsize > 1 for _, dt, _ in specs)
    assert msg.is_bigendian is (big and multibyte)
    assert msg.point_step == sum(dt.itemsize * c for _, dt, c in specs)
    s = cloud_to_structured(msg)
    expect_shape = shape if organized and h > 1 else (h * w,)
    assert s.shape == expect_shape
    assert_fields_equal(s, arr.reshape(expect_shape))
    # The dict form builds the same bytes.
    cols = {n: arr[n].reshape((h * w,) + arr[n].shape[len(shape):]) for n, _, _ in specs}
    assert bytes(create_cloud(None, cols).data) == bytes(msg.data)


# --------------------------------------------------------------------------- real clouds

PCD_TO_CODE = {"f4": 7, "f8": 8, "u1": 2, "u2": 4, "u4": 6, "i1": 1, "i2": 3, "i4": 5}


@pytest.fixture(scope="module")
def realdata():
    d = realdata_dir()
    if not d.is_dir():
        pytest.skip(f"real PCD clouds not found at {d} "
                    "(set LQ_REALDATA to the realdata directory)")
    return d


@pytest.mark.parametrize("stem", REAL_FILES)
def test_real_pcd_clouds(realdata, stem):
    path = realdata / f"{stem}.pcd"
    if not path.exists():
        pytest.skip(f"{path} missing")
    arr, layout, raw = read_pcd(path)
    n = arr.size
    assert n > 1000 and {"x", "y", "z"} <= set(layout.names)

    # 1) Hand-built message with the PCD's exact byte layout.
    fields = [pf(name, layout.fields[name][1],
                 PCD_TO_CODE[layout.fields[name][0].base.str[1:]],
                 layout.fields[name][0].shape[0] if layout.fields[name][0].shape else 1)
              for name in layout.names]
    hand = make_msg(fields, raw, height=arr.shape[0] if arr.ndim == 2 else 1,
                    width=arr.shape[-1], point_step=layout.itemsize)
    # 2) Message built by the module from the decoded array.
    built = create_cloud(Header(frame_id=stem), arr)
    assert bytes(built.data) == raw  # PCD binary is packed little-endian: identical bytes
    assert [(f.name, f.offset, f.datatype, f.count) for f in built.fields] == \
        [(f.name, f.offset, f.datatype, f.count) for f in fields]

    finite_ref = np.isfinite(arr["x"]) & np.isfinite(arr["y"]) & np.isfinite(arr["z"])
    assert built.is_dense is bool(finite_ref.all())
    for msg in (hand, built):
        s = cloud_to_structured(msg)
        assert_fields_equal(s, arr)
        xyz, inten = xyz_intensity(msg)
        ref_xyz = np.stack([arr["x"], arr["y"], arr["z"]], axis=-1).reshape(-1, 3)
        np.testing.assert_array_equal(bits(xyz), bits(ref_xyz))  # NaN positions included
        np.testing.assert_array_equal(finite_mask(xyz), finite_ref.reshape(-1))
        if "intensity" in layout.names:
            np.testing.assert_array_equal(inten, arr["intensity"].astype(np.float32))
        else:
            assert inten is None
        xyz_again = read_fields(msg, ["x", "y", "z"])
        np.testing.assert_array_equal(bits(xyz_again), bits(xyz))
        # lmd's read: a view into the driver's bytes, the same values, the same counts
        view, vi = pc.xyz_intensity_view(msg)
        assert not view.flags.owndata, "a driver layout that is copied, not viewed"
        np.testing.assert_array_equal(bits(view), bits(xyz))
        if inten is not None:
            np.testing.assert_array_equal(vi, inten)
            assert pc.padding_counts(view, vi) == pc.blank_padding(xyz.copy(), inten)
        # lms's read: one pass over the driver's records, the same values and checks
        cols = pc.xyz_columns(s)
        if s.dtype.fields["x"][0] == np.float32:
            got, valid, n_padding = cols
            np.testing.assert_array_equal(bits(got), bits(xyz))
            np.testing.assert_array_equal(valid, pc.valid_points(xyz))
            assert n_padding == int((finite_mask(xyz) & ~pc.valid_points(xyz)).sum())
        else:
            assert cols is None
    # Ranges are those of a real scene, not garbage from a wrong offset.
    ok = ref_xyz[finite_ref.reshape(-1)]
    rng = np.linalg.norm(ok, axis=1)
    assert 0.05 < np.median(rng) < 200

    if stem == "velodyne_vlp16":
        s = cloud_to_structured(hand)
        ch = s["channel"]
        assert ch.dtype == np.dtype("<u2") and ch.min() >= 0 and ch.max() == 15
        assert len(np.unique(ch)) >= 12  # a VLP-16 scan: (nearly) all 16 lasers present
        dist = read_fields(hand, ["distance"])[:, 0]
        np.testing.assert_allclose(dist, np.linalg.norm(xyz_intensity(hand)[0], axis=1),
                                   rtol=1e-3, atol=1e-3)


def test_set_cloud_data_stores_the_buffer_without_a_copy():
    # the one rosidl private slot we write: if a rosidl release renames it, the fallback
    # (the public setter) copies, and this test says so
    import array

    from lidar_quality_core.pointcloud import set_cloud_data
    from sensor_msgs.msg import PointCloud2

    buf = array.array("B", bytes(64))
    msg = PointCloud2()
    set_cloud_data(msg, buf)
    assert msg.data is buf


def test_valid_points_excludes_non_finite_and_zero_padding():
    xyz = np.array([[1, 2, 3], [0, 0, 0], [np.nan, 0, 0], [0, np.inf, 0], [0, 0, 1e-30],
                    [-0.0, 0.0, -0.0], [0, 0, 5]], np.float32)
    np.testing.assert_array_equal(pc.valid_points(xyz),
                                  [True, False, False, False, True, False, True])
    # padding = invalid but finite
    assert int((finite_mask(xyz) & ~pc.valid_points(xyz)).sum()) == 2
    assert pc.valid_points(np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        pc.valid_points(np.zeros((4, 2)))


@pytest.mark.parametrize("seed", range(6))
def test_blank_padding_is_the_mask_and_the_finite_count(seed):
    """blank_padding against its numpy statement: padding rows (either zero sign) become
    NaN, nothing else changes; the count of finite points is taken afterwards, intensity
    included."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 3000))
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    inten = rng.random(n).astype(np.float32)
    for frac, value in ((0.2, 0.0), (0.05, -0.0), (0.05, np.nan), (0.03, np.inf)):
        rows = rng.random(n) < frac
        cols = rng.random((n, 3)) < (0.5 if value in (np.nan, np.inf) else 1.0)
        xyz[rows[:, None] & cols] = value
    inten[rng.random(n) < 0.05] = np.nan
    want = xyz.copy()
    pad = pc.padding_mask(want)
    want[pad] = np.nan
    n_finite = int((finite_mask(want) & np.isfinite(inten)).sum())
    got = pc.blank_padding(xyz, inten if seed % 2 else inten.astype(np.float64))
    assert got == (int(pad.sum()), n_finite)
    np.testing.assert_array_equal(xyz, want)     # NaN where NaN, same bits elsewhere
    for bad in (xyz[:, :2], xyz.astype(np.float64), np.asfortranarray(xyz)):
        with pytest.raises(ValueError):
            pc.blank_padding(bad, inten)
    with pytest.raises(ValueError, match="intensities"):
        pc.blank_padding(xyz, inten[:-1] if n else np.zeros(1, np.float32))


def test_valid_points_of_an_organized_cloud():
    # an Ouster-style organized cloud: no-return pixels are (0, 0, 0)
    grid = np.zeros((4, 8), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    grid["x"][::2] = 5.0
    msg = create_cloud(None, grid)
    assert (msg.height, msg.width) == (4, 8)
    xyz = np.stack([cloud_to_structured(msg)[k].reshape(-1) for k in "xyz"], 1)
    assert pc.valid_points(xyz).sum() == 16


def test_padding_note_said_once_per_stream():
    from lidar_quality_core.pointcloud import PaddingNote

    note = PaddingNote()
    assert note(0, 100) == []                       # nothing to say yet
    first = note(30, 100)
    assert len(first) == 1 and "30 of 100" in first[0] and "points.padding" in first[0]
    assert note(30, 100) == [] and PaddingNote()(5, 10, "input/cloud")[0].startswith("input/cloud")


@pytest.mark.parametrize("layout", ["packed", "padded_point", "row_padding", "float64_x",
                                    "uint8_intensity", "xyz_apart", "unaligned_buffer"])
def test_xyz_intensity_view_equals_the_copies(layout):
    """The view where the layout allows it (read-only, into the message), else the copies
    of xyz_intensity; the same values either way."""
    from lidar_quality_core.pointcloud import padding_counts, xyz_intensity_view

    rng = np.random.default_rng(5)
    height, width, step, row_step = 3, 6, 16, None
    fields = [pf("x", 0, 7), pf("y", 4, 7), pf("z", 8, 7), pf("intensity", 12, 7)]
    if layout == "padded_point":
        step = 32
    elif layout == "row_padding":
        row_step = step * width + 8
    elif layout == "float64_x":
        step = 24
        fields = [pf("x", 0, 8), pf("y", 8, 7), pf("z", 12, 7), pf("intensity", 16, 7)]
    elif layout == "uint8_intensity":
        fields[3] = pf("intensity", 12, 2)
    elif layout == "xyz_apart":
        fields = [pf("x", 0, 7), pf("y", 8, 7), pf("z", 4, 7), pf("intensity", 12, 7)]
    rs = step * width if row_step is None else row_step
    vals = rng.normal(size=rs * height // 4).astype(np.float32)
    vals[::5] = 0.0
    raw = vals.tobytes()
    data = array.array("B", raw)
    if layout == "unaligned_buffer":
        data = memoryview(bytearray(b"\0" + raw))[1:]
    msg = duck_msg(data, fields=fields, height=height, width=width, point_step=step,
                   row_step=rs)
    with np.errstate(over="ignore", invalid="ignore"):
        want = xyz_intensity(msg)
        got = xyz_intensity_view(msg)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    viewed = layout in ("packed", "padded_point", "uint8_intensity")
    assert (not got[0].flags.owndata and not got[0].flags.writeable) == viewed, layout
    xyz = want[0].copy()
    assert padding_counts(got[0], got[1]) == pc.blank_padding(xyz, want[1])


def test_field_run_view():
    from lidar_quality_core.pointcloud import field_run_view

    names = ["a", "b", "c"]
    dt = np.dtype([("x", "<f4"), ("a", "<f4"), ("b", "<f4"), ("c", "<f4"), ("r", "<u2"),
                   ("pad", "<u2")])
    arr = np.zeros((2, 5), dt)
    for k, nm in enumerate(names):
        arr[nm] = np.arange(10, dtype=np.float32).reshape(2, 5) + 100 * k
    v = field_run_view(arr, names)
    assert v.shape == (10, 3) and np.shares_memory(v, arr)
    np.testing.assert_array_equal(v, np.stack([arr[nm].reshape(-1) for nm in names], 1))
    assert field_run_view(arr, ["b", "c"])[3, 1] == 203
    ro = arr.copy()
    ro.flags.writeable = False
    assert not field_run_view(ro, names).flags.writeable
    assert field_run_view(arr, ["a", "c"]) is None                # not one after the other
    assert field_run_view(arr, ["b", "a"]) is None                # not in order
    assert field_run_view(arr, ["a", "nope"]) is None
    assert field_run_view(arr[:0], names) is None
    assert field_run_view(arr[:, ::2], names) is None             # records not contiguous
    for other in (">f4", "<f8"):
        odt = np.dtype([(nm, other) for nm in names])
        assert field_run_view(np.zeros(4, odt), names) is None
    packed = np.dtype({"names": ["r", "a", "b"], "formats": ["u1", "<f4", "<f4"],
                       "offsets": [0, 1, 5], "itemsize": 9})
    un = np.zeros(4, packed)
    un["a"], un["b"] = [1, 2, 3, 4], [5, 6, 7, 8]
    v = field_run_view(un, ["a", "b"])                            # after a uint8: unaligned
    assert not v.flags.aligned and np.shares_memory(v, un)
    np.testing.assert_array_equal(v, [[1, 5], [2, 6], [3, 7], [4, 8]])


@pytest.mark.parametrize("layout", ["xyz_first", "padded", "organized"])
def test_xyz_columns_equal_the_numpy_passes(layout):
    rng = np.random.default_rng(4)
    n = 3000
    xyz = rng.normal(0, 30, (n, 3)).astype(np.float32)
    xyz[::11] = 0.0                                      # padding
    xyz[5::13, 1] = np.nan
    xyz[7::17, 2] = np.inf
    xyz[3] = (-0.0, 0.0, -0.0)                           # padding too, as == 0 says
    xyz[4] = (0.0, 0.0, 1e-30)                           # not padding
    cols = {"intensity": rng.random(n).astype(np.float32), "x": xyz[:, 0], "y": xyz[:, 1],
            "z": xyz[:, 2]} if layout == "padded" else {"x": xyz[:, 0], "y": xyz[:, 1],
                                                           "z": xyz[:, 2]}
    arr = cloud_to_structured(create_cloud(None, cols))   # odd offsets when padded
    if layout == "organized":
        arr = arr.reshape(30, 100)
    got, valid, n_padding = pc.xyz_columns(arr)
    assert got.shape == (n, 3) and got.T.flags.c_contiguous
    np.testing.assert_array_equal(bits(got), bits(xyz))
    np.testing.assert_array_equal(valid, pc.valid_points(xyz))
    assert n_padding == int((finite_mask(xyz) & ~pc.valid_points(xyz)).sum())
    assert n_padding == int((xyz == 0).all(axis=1).sum()) > 200


def test_xyz_columns_leave_other_types_to_the_caller():
    arr = cloud_to_structured(create_cloud(None, {"x": np.zeros(3), "y": np.zeros(3),
                                                  "z": np.zeros(3)}))   # float64
    assert pc.xyz_columns(arr) is None


def test_cloud_layout_is_pack_clouds():
    cols = {"x": np.zeros(4, np.float32), "label": np.zeros(4, np.uint16),
            "v": np.zeros((4, 3), np.float64)}
    packed = pc.pack_cloud(cols)
    dtype, fields = pc.cloud_layout([("x", np.float32, 1), ("label", np.uint16, 1),
                                     ("v", np.float64, 3)])
    assert fields == packed.fields and dtype.itemsize == packed.point_step == 4 + 2 + 24
    big, _ = pc.cloud_layout([("x", np.float32, 1)], big=True)
    assert big.fields["x"][0] == np.dtype(">f4")
    assert len(pc.new_cloud_data(10)) == 10 and not any(pc.new_cloud_data(10))
