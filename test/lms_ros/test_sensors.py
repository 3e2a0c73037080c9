"""Acceptance (issue 16, sensors): every real sensor of ``../shared/realdata`` through a
rosbag2 in the driver's own field layout, the reference segmenter and LMS.

Per sensor: the PCD's fields (nebula's layout: x, y, z, and for VLP-16 intensity,
return_type, channel, azimuth, elevation, distance, time_stamp) are written as the
PointCloud2 of a real bag (``BagWriter``, two frames), read back, segmented by the
reference segmenter (``reference_perception``: probabilities on a second cloud, as its
node publishes them) and run through ``LmsProcessor`` with the sensor's preset and with
the old defaults (64 x 2048, fov 3 / -25 deg, ``ring_field: ring``). Checked: every point
comes out and is accounted for (no segment = invalid + outside the image + lost its pixel),
the share without a pixel is reported and below 5 % with the preset, the frame's issue
level follows the documented thresholds (WARN above ``no_pixel_warn_ratio``, ERROR above
``no_pixel_error_ratio``), and through the real node the /diagnostics level.

Skips, saying so, without ``../shared/realdata`` (or ``$LQ_REALDATA``)."""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from lidar_quality_core.pcd import read_pcd
from lidar_quality_core.pointcloud import create_cloud, read_fields
from lidar_quality_ros.bag_io import BagWriter, read_bag
from lms_ros.lms_node import LmsNode
from lms_ros.pipeline import (CLASS_NAMES, LmsParameters, LmsProcessor, LmsSettings,
                              load_models)
from lms_scans import header
from node_shell_checks import diag_values, wait_until
from realdata import PRESETS, REAL_FILES, require_realdata
from sensor_msgs.msg import PointCloud2

TOPIC = "/sensing/lidar/top/pointcloud_raw_ex"
BEFORE = LmsSettings(ring_field="ring")      # the defaults before issue 16
TABLE: dict[str, tuple[float, float]] = {}   # stem -> (share before, share after)


@pytest.fixture(scope="module")
def realdata():
    return require_realdata()


@pytest.fixture(scope="module")
def segmenter():
    from reference_perception.segmenter import ReferenceSegmenter

    return ReferenceSegmenter.load()


def write_sensor_bag(path, pcd_path, frames=2):
    """A rosbag2 (MCAP) with ``frames`` PointCloud2 messages of the PCD's points in its
    own field layout; the number of points."""
    arr = read_pcd(pcd_path)[0]
    with BagWriter(path) as w:
        for k in range(frames):
            msg = create_cloud(header(100 + k, "lidar_top"), arr)
            w.write(TOPIC, "sensor_msgs/msg/PointCloud2", msg.header.stamp.sec * 10**9, msg)
    return arr.size, arr.dtype.names


def perception(seg, points):
    """The reference segmenter's probability cloud for ``points`` (its node's output)."""
    from reference_perception.cloud_input import read_cloud
    from reference_perception.messages import probability_cloud

    c = read_cloud(points)
    probs = seg.predict_proba(c.xyz, c.intensity, c.ring)
    return probability_cloud(points.header, c.xyz, c.intensity, probs, CLASS_NAMES)


def check_frame(out, points, settings):
    """Every point out and accounted for; the issue level follows the thresholds."""
    n = points.width * points.height
    assert out.points.width * out.points.height == n
    np.testing.assert_array_equal(read_fields(out.points, ["x", "y", "z"]),
                                  read_fields(points, ["x", "y", "z"]))
    seg = read_fields(out.points, ["segment"], dtype=np.int64)[:, 0]
    c = out.counts
    assert c["points.in"] == n
    assert c["points.no_segment"] == int((seg < 0).sum()) == (
        c["points.invalid"] + c["points.unprojected"] + c["points.occluded"])
    ratio = out.values["points.no_pixel_ratio"]
    valid = n - c["points.invalid"]
    assert ratio == pytest.approx((c["points.unprojected"] + c["points.occluded"]) / valid)
    assert ("unprojected" in out.issues) == (ratio > settings.no_pixel_warn_ratio)
    assert ("unprojected" in out.errors) == (ratio > settings.no_pixel_error_ratio)
    return ratio


@pytest.mark.parametrize("stem", REAL_FILES)
def test_real_sensor_bag_with_its_preset(realdata, segmenter, tmp_path, stem):
    n, fields = write_sensor_bag(tmp_path / "bag", realdata / f"{stem}.pcd")
    after = LmsSettings(sensor=PRESETS[stem])
    warned: list[str] = []      # the preset's image is not the shipped models' (a warning)
    procs = {"before": LmsProcessor(BEFORE, load_models(LmsParameters(settings=BEFORE))),
             "after": LmsProcessor(after, load_models(LmsParameters(settings=after),
                                                      warn=warned.append))}
    assert any("channels: model trained with 64" in w or "width: model trained with 2048"
               in w for w in warned), warned
    msgs = [m.decode() for m in read_bag(tmp_path / "bag")]
    assert len(msgs) == 2 and all(m.width * m.height == n for m in msgs)
    assert [f.name for f in msgs[0].fields] == list(fields)      # the driver's layout
    shares = {}
    for points in msgs:
        probs = perception(segmenter, points)
        for name, proc in procs.items():
            out = proc.process(points, probs)
            shares[name] = check_frame(out, points, proc.settings)
    before, share = shares["before"], shares["after"]
    TABLE[stem] = (before, share)
    # with its preset every sensor's image holds (nearly) every point
    assert share < 0.05, f"{stem} ({PRESETS[stem]}): {100 * share:.1f} % without a pixel"
    assert share < before


@pytest.mark.parametrize("params, level", [
    ({"ring_field": "ring"}, DiagnosticStatus.ERROR), ({"sensor": "VLP-16"}, DiagnosticStatus.OK)],
    ids=["old_defaults", "preset"])
def test_vlp16_diagnostics_levels(ros, realdata, segmenter, tmp_path, params, level):
    """Through the node (two inputs: nebula's cloud and the segmenter's probabilities):
    the old defaults leave two thirds of a VLP-16 without a pixel: /diagnostics ERROR,
    naming it, the frame still published; the preset: OK (the image differs from the
    shipped models': a logged warning and the value model.geometry)."""
    write_sensor_bag(tmp_path / "bag", realdata / "velodyne_vlp16.pcd", frames=1)
    points = next(iter(read_bag(tmp_path / "bag"))).decode()
    probs = perception(segmenter, points)
    node = ros.start(LmsNode, parameters={**params, "separate_probabilities": True})
    pub_p = ros.sensor_publisher(PointCloud2, "input/points")
    pub_q = ros.sensor_publisher(PointCloud2, "input/probabilities")
    out = ros.collector(PointCloud2, "output/points")
    assert ros.wait_for_match(pub_p) and ros.wait_for_match(pub_q)
    assert ros.wait_for_match(out.subscription)
    pub_q.publish(probs)
    pub_p.publish(points)
    assert out.wait_for(1, timeout=30.0)
    assert out.messages[0].width == points.width
    assert wait_until(lambda: node.diag.frames_out == 1)
    st = node.diag.status()
    values = diag_values(st)
    assert st.level == level, st.message
    ratio = float(values["points.no_pixel_ratio"])
    assert int(values["points.in"]) == points.width and node.diag.dropped == 0
    if level == DiagnosticStatus.ERROR:
        assert ratio > 0.5 and "have no pixel" in st.message, st.message
        assert values["image"] == "custom: 64 x 2048"
    else:
        assert ratio < 0.05 and values["image"] == "VLP-16: 16 x 1800"
        assert values["model.geometry"].startswith("trained 64 x 2048")


def test_zz_print_table():
    """The closing note's table (run with -s to see it)."""
    if not TABLE:
        pytest.skip("no sensor ran (realdata missing)")
    print("\n| sensor | preset | without a pixel, old defaults | with the preset |")
    print("|---|---|---|---|")
    for stem, (b, a) in TABLE.items():
        print(f"| {stem} | {PRESETS[stem]} | {100 * b:.1f} % | {100 * a:.2f} % |")
