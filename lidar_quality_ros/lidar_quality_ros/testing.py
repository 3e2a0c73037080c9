"""In-process test harness: each test gets its own rclpy Context, DDS domain and executor.

Use as a pytest plugin (``pytest_plugins = ["lidar_quality_ros.testing"]``) for the
``ros`` fixture, or directly::

    with RosHarness() as ros:
        node = ros.start(MyNode, parameters={"sync_mode": "exact"})
        pub = ros.publisher(PointCloud2, "input/points")
        out = ros.collector(Detection3DArray, "output/detections")
        ros.wait_for_match(pub)
        pub.publish(msg)
        assert out.wait_for(1, timeout=5.0)
"""
from __future__ import annotations

import os
import subprocess
import threading
import time
import traceback
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter

from .domain import DomainLease
from .executors import SubmitOnceExecutor
from .qos import SENSOR_QOS, output_qos


class Collector:
    """Thread-safe list of the messages received on one topic."""

    def __init__(self):
        self.messages: list = []
        self.subscription = None
        self.receive_times: list[float] = []
        self._cond = threading.Condition()

    def __call__(self, msg) -> None:
        with self._cond:
            self.messages.append(msg)
            self.receive_times.append(time.monotonic())
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self.messages)

    def wait_for(self, n: int = 1, timeout: float = 10.0) -> bool:
        """True once ``n`` messages arrived, False after ``timeout`` seconds."""
        with self._cond:
            return self._cond.wait_for(lambda: len(self.messages) >= n, timeout=timeout)


class RosHarness:
    """A private ROS world for one test (own Context, leased domain id, executor thread)."""

    def __init__(self, num_threads: int = 2):
        self.lease = DomainLease.acquire()
        self.domain_id = self.lease.domain_id
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        # num_threads=1: a SingleThreadedExecutor, far cheaper per callback (load tests,
        # the demo's recorder); 2 lets an in-process node under test wait in a callback.
        self.executor = (SingleThreadedExecutor(context=self.context) if num_threads <= 1 else
                         SubmitOnceExecutor(num_threads=num_threads, context=self.context))
        self.node = rclpy.create_node(f"lq_test_harness_{os.getpid()}", context=self.context)
        self.executor.add_node(self.node)
        self._nodes = [self.node]
        self._procs: list[subprocess.Popen] = []
        self.errors: list[str] = []
        self._closing = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        # spin() keeps its wait set (spin_once rebuilds it: too slow at sensor rates).
        # After a callback raised, remember it (close() fails the test) and spin on.
        while self.context.ok() and not self._closing:
            try:
                self.executor.spin()
            except ExternalShutdownException:
                break
            except Exception:  # noqa: BLE001 - recorded: close() fails the test
                if self.context.ok() and not self._closing:
                    self.errors.append(traceback.format_exc())

    # nodes under test -------------------------------------------------------------
    def start(self, node_cls, parameters: dict[str, Any] | None = None, **kwargs):
        """Construct ``node_cls`` in this context with parameter overrides and spin it."""
        overrides = [Parameter(k, value=v) for k, v in (parameters or {}).items()]
        node = node_cls(context=self.context, parameter_overrides=overrides, **kwargs)
        self.executor.add_node(node)
        self._nodes.append(node)
        return node

    def env(self) -> dict[str, str]:
        """Environment for a subprocess that must join this test's domain (loopback only)."""
        env = dict(os.environ)
        env.update(ROS_DOMAIN_ID=str(self.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        return env

    def spawn(self, argv: list[str], extra_env: dict[str, str] | None = None,
              **kwargs) -> subprocess.Popen:
        """Start a process (e.g. a node executable) in this test's domain."""
        proc = subprocess.Popen(argv, env={**self.env(), **(extra_env or {})}, **kwargs)
        self._procs.append(proc)
        return proc

    # topics -----------------------------------------------------------------------
    def publisher(self, msg_type, topic: str, qos=None):
        return self.node.create_publisher(msg_type, topic, qos if qos is not None else output_qos(10))

    def collector(self, msg_type, topic: str, qos=None) -> Collector:
        col = Collector()
        col.subscription = self.node.create_subscription(
            msg_type, topic, col, qos if qos is not None else output_qos(50))
        return col

    def sensor_publisher(self, msg_type, topic: str):
        return self.publisher(msg_type, topic, SENSOR_QOS)

    def wait_for_match(self, endpoint, n: int = 1, timeout: float = 10.0) -> bool:
        """Wait until a publisher has ``n`` subscriptions (or a subscription ``n`` publishers)."""
        count = (endpoint.get_subscription_count if hasattr(endpoint, "get_subscription_count")
                 else endpoint.get_publisher_count)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if count() >= n:
                return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        self._closing = True
        for proc in self._procs:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        self.executor.shutdown(timeout_sec=2.0)
        for node in reversed(self._nodes):
            node.destroy_node()
        self.context.try_shutdown()
        self._thread.join(timeout=5.0)
        self.lease.release()
        if self.errors:
            raise AssertionError("callbacks raised in the ROS harness:\n" + "\n".join(self.errors))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


try:
    import pytest

    @pytest.fixture
    def ros():
        """A private ROS world (own Context, domain and executor) for one test."""
        harness = RosHarness()
        try:
            yield harness
        finally:
            harness.close()
except ImportError:  # pytest is only needed for the fixture
    pass
