"""lmd_node shell: parameters, sensor QoS inputs, pass-through, bad input, clean shutdown."""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lidar_quality_core.boxes import arrays_to_detections
from lidar_quality_core.pointcloud import create_xyz_cloud
from lmd_ros.lmd_node import LmdNode
from node_shell_checks import (assert_declared_with_descriptions, assert_sensor_qos,
                               assert_yaml_matches_declared, diag_values,
                               run_executable_and_signal, wait_until)
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from vision_msgs.msg import Detection3DArray


def _frame(sec, n_boxes=3, seed=0):
    rng = np.random.default_rng(seed)
    h = Header(frame_id="lidar_top")
    h.stamp.sec = sec
    cloud = create_xyz_cloud(h, rng.normal(size=(2000, 3)).astype(np.float32),
                             rng.random(2000).astype(np.float32))
    boxes = np.column_stack([rng.normal(size=(n_boxes, 3)), np.full((n_boxes, 3), 2.0),
                             rng.uniform(-3, 3, n_boxes)])
    dets = arrays_to_detections(h, boxes, ["car"] * n_boxes, rng.random(n_boxes),
                                ids=[f"det{sec}_{i}" for i in range(n_boxes)])
    return cloud, dets


def test_parameters(ros):
    node = ros.start(LmdNode)
    assert_declared_with_descriptions(node, {"use_proposals", "sync_mode", "sync_slop",
                                             "sync_queue_size", "diagnostics_period"})
    assert_yaml_matches_declared(node, "lmd_ros")


def test_inputs_use_sensor_qos(ros):
    node = ros.start(LmdNode, parameters={"use_proposals": True})
    for topic in ("input/points", "input/detections", "input/proposals"):
        assert_sensor_qos(node, topic)


def test_detections_pass_through_in_order(ros):
    ros.start(LmdNode)
    pc = ros.sensor_publisher(PointCloud2, "input/points")
    dp = ros.sensor_publisher(Detection3DArray, "input/detections")
    out = ros.collector(Detection3DArray, "output/detections")
    assert ros.wait_for_match(pc) and ros.wait_for_match(dp)
    sent = []
    for sec in range(1, 4):
        cloud, dets = _frame(sec, n_boxes=sec + 1, seed=sec)
        dp.publish(dets)  # detections before the cloud: the synchroniser must wait
        pc.publish(cloud)
        sent.append(dets)
        assert out.wait_for(sec, timeout=10.0)
    for got, want in zip(out.messages, sent):
        assert got.header == want.header
        assert [d.id for d in got.detections] == [d.id for d in want.detections]
        assert got == want


def test_malformed_cloud_is_counted_not_fatal(ros):
    node = ros.start(LmdNode, parameters={"diagnostics_period": 0.2})
    pc = ros.sensor_publisher(PointCloud2, "input/points")
    dp = ros.sensor_publisher(Detection3DArray, "input/detections")
    out = ros.collector(Detection3DArray, "output/detections")
    diag = ros.collector(DiagnosticArray, "/diagnostics")
    assert ros.wait_for_match(pc) and ros.wait_for_match(dp)
    cloud, dets = _frame(7)
    cloud.data = cloud.data[:100]  # truncated buffer
    pc.publish(cloud)
    dp.publish(dets)
    assert wait_until(lambda: node.diag.dropped == 1)
    status = node.diag.status()
    assert status.level == DiagnosticStatus.WARN and "input/points" in status.message
    assert diag_values(status)["dropped.malformed_cloud"] == "1"
    assert diag.wait_for(1, timeout=5.0)
    good_cloud, good_dets = _frame(8)
    pc.publish(good_cloud)
    dp.publish(good_dets)
    assert out.wait_for(1, timeout=10.0)
    assert out.messages[0].header.stamp.sec == 8  # the bad frame produced no output
    assert node.diag.dropped == 1
    assert node.diag.status().level == DiagnosticStatus.OK  # the good frame cleared it


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_executable_starts_and_stops_cleanly(ros, signame):
    run_executable_and_signal(ros, "lmd_ros", "lmd_node", ["input/points", "input/detections"],
                              signame)


def test_launch_file():
    from node_shell_checks import assert_launch_file
    assert_launch_file("lmd_ros", "lmd_node")


def test_signal_while_frames_are_processed(ros):
    """SIGINT in the middle of a stream: the frame in flight finishes, the exit is clean
    (with rclpy's default handlers this crashed about one run in six)."""
    import signal
    import subprocess
    import time

    from node_shell_checks import executable
    frames = [_frame(sec, n_boxes=20, seed=sec) for sec in range(1, 6)]
    for trial in range(5):
        proc = ros.spawn([str(executable("lmd_ros", "lmd_node")), "--ros-args",
                          "-r", "__node:=lmd_stream"], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, extra_env={"PYTHONFAULTHANDLER": "1"})
        pc = ros.sensor_publisher(PointCloud2, "input/points")
        dp = ros.sensor_publisher(Detection3DArray, "input/detections")
        out = ros.collector(Detection3DArray, "output/detections")
        assert ros.wait_for_match(pc) and ros.wait_for_match(dp) and ros.wait_for_match(out.subscription)
        # The node may match our writers later than we match its reader (best effort
        # samples before that are lost): stream until outputs flow, then signal mid-stream.
        # Discovery of our writers by the new node process occasionally waits for
        # Fast DDS's periodic announcements (seconds): bound the wait in time, not frames.
        k, signalled_at, deadline = 0, None, time.monotonic() + 60.0
        while signalled_at is None or k < signalled_at + 15:
            cloud, dets = frames[k % len(frames)]
            cloud.header.stamp.sec = dets.header.stamp.sec = 1000 * trial + k + 1
            pc.publish(cloud)
            dp.publish(dets)
            if signalled_at is None and len(out) >= 3 + trial:
                proc.send_signal(signal.SIGINT)
                signalled_at = k
            if signalled_at is None and time.monotonic() > deadline:
                proc.kill()
                raise AssertionError(f"trial {trial}: lmd_node produced {len(out)} outputs; "
                                     f"exit {proc.poll()}; log:\n{proc.communicate()[0][-3000:]}")
            k += 1
            time.sleep(0.005)
        text, _ = proc.communicate(timeout=20)
        assert proc.returncode == 0, f"trial {trial}: exit {proc.returncode}\n{text[-3000:]}"
        assert len(out) > 0
        for sub in (pc, dp):
            ros.node.destroy_publisher(sub)
        ros.node.destroy_subscription(out.subscription)
