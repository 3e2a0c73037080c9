"""Acceptance (issue 16): every real sensor of ``../shared/realdata`` as a user's bag (the
driver's own point layout, the user's topic names), through the reference perception
(``reference-perception bag``) and the three nodes (``process_bag``, LMS with the sensor's
preset), with no silent drop: every frame out, or dropped and counted with its reason.

Most of the driver's decoded clouds carry x, y, z only: LMD (whose reflectance features
need intensity) drops such frames as ``malformed_cloud``, counted and said; LMS and MIMO
process them. Skips, saying so, without ``../shared/realdata`` (or ``$LQ_REALDATA``)."""
import numpy as np
import pytest
from lidar_quality_core.pcd import read_pcd
from lidar_quality_core.pointcloud import create_cloud
from lidar_quality_ros.bag_io import BagWriter
from lidar_quality_tools.process import process_bag
from realdata import PRESETS, REAL_FILES, require_realdata
from reference_perception.cli import main as perception_main
from std_msgs.msg import Header

TOPIC = "/sensing/lidar/top/pointcloud"
FRAMES = 2


@pytest.fixture(scope="module")
def realdata():
    return require_realdata()


def users_bag(path, pcd):
    arr = read_pcd(pcd)[0]
    with BagWriter(path) as w:
        for k in range(FRAMES):
            h = Header(frame_id="lidar_top")
            h.stamp.sec = 1_700_000_000 + k
            w.write(TOPIC, "sensor_msgs/msg/PointCloud2", h.stamp.sec * 10**9,
                    create_cloud(h, arr))
    return arr


@pytest.mark.parametrize("stem", REAL_FILES)
def test_real_sensor_through_perception_and_the_three_nodes(realdata, tmp_path, stem):
    arr = users_bag(tmp_path / "users", realdata / f"{stem}.pcd")
    perceived = tmp_path / "perceived"
    assert perception_main(["bag", "--in", str(tmp_path / "users"), "--out", str(perceived),
                            "--quiet", "--topic", f"points={TOPIC}"]) == 0
    s = process_bag(perceived, tmp_path / "out", progress=False, topics={"points": TOPIC},
                    params={"lms.sensor": PRESETS[stem]})
    nodes = s["nodes"]
    has_intensity = any(n in arr.dtype.names for n in ("intensity", "reflectance", "i"))
    for name, n in nodes.items():
        assert n["frames_in"] == FRAMES, (name, n)
        # no silent drop: every frame either came out or is counted with its reason
        assert n["frames_out"] + n["frames_dropped"] == FRAMES, (name, n)
    assert nodes["lms"]["frames_out"] == FRAMES and nodes["mimo"]["frames_out"] == FRAMES
    lmd = nodes["lmd"]
    if has_intensity:
        assert lmd["frames_out"] == FRAMES, lmd
    else:
        assert lmd["dropped"] == {"malformed_cloud": FRAMES}, lmd
    lms = nodes["lms"]
    # every point accounted for: in = segmented + without a segment (each counted)
    c = lms["counts"]
    assert c["points.in"] == FRAMES * arr.size
    assert c["points.no_segment"] == (c["points.invalid"] + c["points.unprojected"]
                                      + c["points.occluded"])
    ratio = float(lms["values"]["points.no_pixel_ratio"])
    assert ratio < 0.05, (stem, ratio)
    assert "unprojected" not in lms["issues"]
    assert np.isfinite(ratio)
