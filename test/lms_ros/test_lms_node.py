"""lms_node shell: parameters, sensor QoS input, pass-through, bad input, clean shutdown."""
import numpy as np
import pytest
from lidar_quality_core.pointcloud import create_xyz_cloud
from lms_ros.lms_node import LmsNode
from node_shell_checks import (assert_declared_with_descriptions, assert_sensor_qos,
                               assert_yaml_matches_declared, run_executable_and_signal,
                               wait_until)
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header


def _cloud(sec):
    h = Header(frame_id="lidar_top")
    h.stamp.sec = sec
    rng = np.random.default_rng(sec)
    return create_xyz_cloud(h, rng.normal(size=(500, 3)).astype(np.float32),
                            rng.random(500).astype(np.float32))


def test_parameters_and_qos(ros):
    node = ros.start(LmsNode)
    assert_declared_with_descriptions(node, {"sync_mode", "sync_slop", "sync_queue_size",
                                             "diagnostics_period"})
    assert_yaml_matches_declared(node, "lms_ros")
    assert_sensor_qos(node, "input/points")


def test_cloud_passes_through_and_bad_cloud_is_counted(ros):
    node = ros.start(LmsNode)
    pub = ros.sensor_publisher(PointCloud2, "input/points")
    out = ros.collector(PointCloud2, "output/points")
    assert ros.wait_for_match(pub)
    bad = _cloud(1)
    bad.fields = [PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1)]
    pub.publish(bad)  # no y / z field
    good = _cloud(2)
    pub.publish(good)
    assert out.wait_for(1, timeout=10.0)
    assert out.messages[0] == good
    assert wait_until(lambda: node.diag.dropped == 1)


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_executable_starts_and_stops_cleanly(ros, signame):
    run_executable_and_signal(ros, "lms_ros", "lms_node", ["input/points"], signame)


def test_launch_file():
    from node_shell_checks import assert_launch_file
    assert_launch_file("lms_ros", "lms_node")
