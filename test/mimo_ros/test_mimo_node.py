"""mimo_node shell: parameters, K head inputs with sensor QoS, matching, clean shutdown."""
import numpy as np
import pytest
from lidar_quality_core.boxes import arrays_to_detections
from mimo_ros.mimo_node import MimoNode
from node_shell_checks import (assert_declared_with_descriptions, assert_sensor_qos,
                               assert_yaml_matches_declared, diag_values,
                               run_executable_and_signal, wait_until)
from std_msgs.msg import Header
from vision_msgs.msg import Detection3DArray


def test_parameters_and_head_inputs(ros):
    node = ros.start(MimoNode, parameters={"num_heads": 3})
    assert_declared_with_descriptions(node, {"num_heads", "sync_mode", "sync_slop",
                                             "sync_queue_size", "diagnostics_period"})
    assert_yaml_matches_declared(node, "mimo_ros")
    for k in range(3):
        assert_sensor_qos(node, f"input/head_{k}")
    assert node.inputs.topics == ["input/head_0", "input/head_1", "input/head_2"]


def test_num_heads_range(ros):
    with pytest.raises(Exception, match="num_heads"):
        ros.start(MimoNode, parameters={"num_heads": 0})


def test_heads_are_matched_by_stamp(ros):
    node = ros.start(MimoNode, parameters={"num_heads": 2})
    pubs = [ros.sensor_publisher(Detection3DArray, f"input/head_{k}") for k in range(2)]
    assert all(ros.wait_for_match(p) for p in pubs)
    h = Header(frame_id="lidar")
    boxes = np.array([[5.0, 1.0, 0.0, 4.0, 2.0, 1.5, 0.1]])
    for sec in (1, 2):
        h.stamp.sec = sec
        for p in pubs:
            p.publish(arrays_to_detections(h, boxes, ["car"], [0.9]))
    h.stamp.sec = 3  # head 1 never sends frame 3
    pubs[0].publish(arrays_to_detections(h, boxes, ["car"], [0.9]))
    assert wait_until(lambda: node.diag.frames_out == 2)
    assert diag_values(node.diag.status())["sync.matched"] == "2"


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_executable_starts_and_stops_cleanly(ros, signame):
    run_executable_and_signal(ros, "mimo_ros", "mimo_node", ["input/head_0", "input/head_1"],
                              signame)


def test_launch_file():
    from node_shell_checks import assert_launch_file
    assert_launch_file("mimo_ros", "mimo_node")


def test_bad_parameter_exits_with_code_2(ros):
    import subprocess

    from node_shell_checks import executable
    proc = ros.spawn([str(executable("mimo_ros", "mimo_node")), "--ros-args", "-p", "num_heads:=0"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2, out
    assert "node failed to start" in out and "num_heads" in out
