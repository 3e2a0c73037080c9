"""Checks shared by the node-shell tests of lmd_ros, lms_ros and mimo_ros."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import yaml
from rclpy.qos import ReliabilityPolicy

WS_INSTALL = Path(__file__).resolve().parents[2] / "ros2_ws" / "install"


def diag_values(status) -> dict[str, str]:
    return {v.key: v.value for v in status.values}


def assert_declared_with_descriptions(node, expected: set[str]) -> None:
    declared = {n for n in node._parameters if n != "use_sim_time"}
    assert expected <= declared, f"missing parameters: {expected - declared}"
    for name in declared:
        assert node.describe_parameter(name).description, f"{name} has no description"


def assert_yaml_matches_declared(node, package: str) -> None:
    """The shipped config YAML sets only declared parameters, with the declared types."""
    path = WS_INSTALL / package / "share" / package / "config" / f"{node.get_name()}.yaml"
    params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    for name, value in params.items():
        assert node.has_parameter(name), f"{path.name} sets undeclared parameter {name}"
        assert type(node.get_parameter(name).value) is type(value), name


def assert_sensor_qos(node, topic: str) -> None:
    infos = node.get_subscriptions_info_by_topic(node.resolve_topic_name(topic))
    ours = [i for i in infos if i.node_name == node.get_name()]
    assert ours, f"{node.get_name()} has no subscription on {topic}"
    assert ours[0].qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT


def executable(package: str, name: str) -> Path:
    path = WS_INSTALL / package / "lib" / package / name
    assert path.is_file() and os.access(path, os.X_OK), f"{path} not installed"
    return path


def run_executable_and_signal(ros, package, name, inputs, signame, timeout=20.0):
    """Start the installed executable (ros2 run layout) in the test's domain, wait until
    its subscriptions appear, send the signal and require a clean exit (code 0)."""
    proc = ros.spawn([str(executable(package, name)), "--ros-args", "-r", f"__node:={name}_under_test"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + timeout
    seen = set()
    while time.monotonic() < deadline and seen != set(inputs):
        assert proc.poll() is None, f"{name} exited early:\n{proc.stdout.read()}"
        seen = {t for t in inputs
                if any(i.node_name == f"{name}_under_test"
                       for i in ros.node.get_subscriptions_info_by_topic("/" + t))}
        time.sleep(0.1)
    assert seen == set(inputs), f"{name} did not subscribe to {set(inputs) - seen}"
    proc.send_signal(getattr(signal, signame))
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError(f"{name} did not exit on {signame}")
    assert proc.returncode == 0, f"{name} exited with {proc.returncode} on {signame}:\n{out}"
    assert "Traceback" not in out, out


def assert_launch_file(package: str, node_name: str) -> None:
    """The installed launch file parses and starts ``node_name`` with its params file.

    launch / launch_ros are not installable from PyPI here, so the file is checked
    statically; on a Jazzy installation `ros2 launch` runs it.
    """
    import ast
    short = node_name.removesuffix("_node")
    path = WS_INSTALL / package / "share" / package / "launch" / f"{short}.launch.py"
    tree = ast.parse(path.read_text(), filename=str(path))
    funcs = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in funcs
    consts = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)}
    assert {package, node_name, f"{node_name}.yaml", "config"} <= consts, consts


def wait_until(predicate, timeout: float = 10.0) -> bool:
    """Poll ``predicate`` until true (callbacks run on executor threads) or timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()
