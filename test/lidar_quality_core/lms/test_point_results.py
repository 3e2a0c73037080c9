"""The LMS output records written in one pass against ``pointcloud.pack_cloud`` of the same
columns built with numpy (the code they replaced), byte for byte."""
import numpy as np
import pytest

from lidar_quality_core.lms.point_results import RESULT_LAYOUT, pack_point_results
from lidar_quality_core.pointcloud import cloud_to_structured, pack_cloud


def reference(xyz, point_class, point_segment, conf, iou, label=None):
    """pack_cloud of the columns (the NaN row after the per-segment values)."""
    def per_point(v):
        t = np.append(np.asarray(v, np.float32), np.float32(np.nan))
        return t[point_segment]
    return pack_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                       "label": point_class.astype(np.uint16) if label is None else label,
                       "segment": point_segment, "confidence": per_point(conf),
                       "predicted_iou": per_point(iou)})


def frame(n=5000, ns=300, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 20, (3, n)).astype(np.float32).T    # column views, as the node's
    pc = rng.integers(0, 14, n).astype(np.int32)
    ps = rng.integers(-1, ns, n).astype(np.int32)
    conf = rng.random(ns)
    conf[::7] = np.nan                                         # excluded segments
    iou = rng.random(ns)
    return xyz, pc, ps, conf, iou


def test_bytes_and_layout_are_pack_clouds():
    xyz, pc, ps, conf, iou = frame()
    got = pack_point_results(xyz, pc, ps, conf, iou)
    want = reference(xyz, pc, ps, conf, iou)
    assert bytes(got.data) == bytes(want.data)
    assert got.fields == want.fields
    assert (got.point_step, got.is_bigendian, got.is_dense) == (
        want.point_step, want.is_bigendian, want.is_dense) == (26, False, True)
    assert [nm for nm, _, _ in RESULT_LAYOUT] == [f[0] for f in got.fields]


def test_values_read_back():
    xyz, pc, ps, conf, iou = frame(n=50, ns=5, seed=3)
    p = pack_point_results(xyz, pc, ps, conf, iou)
    rec = np.frombuffer(p.data, np.dtype({"names": [f[0] for f in p.fields],
                                          "formats": ["<f4"] * 3 + ["<u2", "<i4", "<f4", "<f4"],
                                          "offsets": [f[1] for f in p.fields],
                                          "itemsize": p.point_step}))
    np.testing.assert_array_equal(rec["x"], xyz[:, 0])
    np.testing.assert_array_equal(rec["label"], pc)
    np.testing.assert_array_equal(rec["segment"], ps)
    none = ps < 0
    assert np.isnan(rec["confidence"][none]).all() and np.isnan(rec["predicted_iou"][none]).all()
    np.testing.assert_array_equal(rec["confidence"][~none], conf[ps[~none]].astype(np.float32))
    np.testing.assert_array_equal(rec["predicted_iou"][~none], iou[ps[~none]].astype(np.float32))


def test_label_override_non_finite_points_and_rows():
    xyz, pc, ps, conf, iou = frame(n=600, ns=40, seed=1)
    xyz = np.array(xyz)
    xyz[3, 1] = np.nan
    xyz[9, 2] = -np.inf
    label = pc.astype(np.uint16)
    label[::5] = 65535
    got = pack_point_results(xyz, pc, ps, conf, iou, label=label, height=20)
    want = reference(xyz, pc, ps, conf, iou, label=label)
    assert bytes(got.data) == bytes(want.data)
    assert not got.is_dense and not want.is_dense
    assert (got.height, got.width) == (20, 30)


def test_float64_coordinates_are_cast_as_pack_cloud_casts():
    xyz, pc, ps, conf, iou = frame(n=300, ns=10, seed=2)
    x64 = xyz.astype(np.float64) + 1e-9
    got = pack_point_results(x64, pc, ps, conf, iou)
    assert bytes(got.data) == bytes(reference(x64.astype(np.float32), pc, ps, conf, iou).data)


def test_empty_and_all_without_segment():
    p = pack_point_results(np.zeros((0, 3), np.float32), np.zeros(0, np.int32),
                           np.zeros(0, np.int32), np.zeros(0), np.zeros(0))
    assert len(p.data) == 0 and p.width == 0 and p.is_dense
    xyz, pc, _, _, _ = frame(n=10)
    p = pack_point_results(xyz, pc, np.full(10, -1, np.int32), np.zeros(0), np.zeros(0))
    assert bytes(p.data) == bytes(reference(xyz, pc, np.full(10, -1, np.int32),
                                            np.zeros(0), np.zeros(0)).data)


def test_bad_arguments_raise_instead_of_reading_out_of_bounds():
    xyz, pc, ps, conf, iou = frame(n=100, ns=10)
    with pytest.raises(ValueError, match="segment"):
        pack_point_results(xyz, pc, np.full(100, 10, np.int32), conf, iou)
    with pytest.raises(ValueError, match="entries"):
        pack_point_results(xyz, pc[:50], ps, conf, iou)
    with pytest.raises(ValueError, match="one value per segment"):
        pack_point_results(xyz, pc, ps, conf, iou[:5])
    with pytest.raises(ValueError, match="rows"):
        pack_point_results(xyz, pc, ps, conf, iou, height=3)


def test_decodes_as_a_cloud():
    from sensor_msgs.msg import PointCloud2, PointField
    from lidar_quality_core.pointcloud import set_cloud_data

    xyz, pc, ps, conf, iou = frame(n=64, ns=8)
    p = pack_point_results(xyz, pc, ps, conf, iou, height=4)
    msg = PointCloud2(height=p.height, width=p.width, point_step=p.point_step,
                      row_step=p.point_step * p.width, is_dense=p.is_dense,
                      fields=[PointField(name=n, offset=o, datatype=d, count=c)
                              for n, o, d, c in p.fields])
    set_cloud_data(msg, p.data)
    arr = cloud_to_structured(msg)
    assert arr.shape == (4, 16)
    np.testing.assert_array_equal(arr["segment"].reshape(-1), ps)


def test_written_into_a_given_buffer_as_into_a_new_one():
    xyz, pc, ps, conf, iou = frame(n=300, ns=20, seed=5)
    want = pack_point_results(xyz, pc, ps, conf, iou)
    buf = np.full(300 * 26 + 7, 0xAB, np.uint8)     # a message around the records
    out = buf[3:-4]
    got = pack_point_results(xyz, pc, ps, conf, iou, out=out)
    assert got.data is out and bytes(out) == bytes(want.data)
    assert (got.fields, got.point_step, got.is_dense) == (want.fields, 26, want.is_dense)
    assert (buf[:3] == 0xAB).all() and (buf[-4:] == 0xAB).all()   # nothing written outside
    for bad in (np.empty(300 * 26 - 1, np.uint8), np.empty(300 * 26, np.int8),
                np.frombuffer(bytes(300 * 26), np.uint8)):             # short, typed, read-only
        with pytest.raises(ValueError, match="writable uint8"):
            pack_point_results(xyz, pc, ps, conf, iou, out=bad)
