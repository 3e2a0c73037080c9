"""Does a PointCloud2 of a given size cross the Fast DDS profile between two processes?

Run each role in the environment under test (``scripts/with_env.sh``), in one domain:

    cloud_probe.py sub SECONDS         # prints "received <bytes>" / "lost <n>", then "done"
    cloud_probe.py pub MB[,MB...] PID  # one cloud per size, then 1 kB ones (end markers)

The subscriber takes clouds as our nodes do (sensor-data QoS, raw bytes: no decoding cost).
The publisher stops the subscriber (SIGSTOP) around each publication and lets it go on
0.5 s after it: a cloud arrives only if all its fragments fit in what the transport holds
for a receiver that is busy for a moment, so the outcome does not depend on the machine's
load. The small cloud at the end makes Fast DDS report the lost ones ("lost <n>"); it is
sent three times, 1 s apart, because one published while the transport is still busy with
a lost cloud's fragments may not arrive (in one of two clean-clone test runs, 2026-12-06,
lms_node saw neither the end marker nor a loss after the 72 MB cloud). The subscriber stops
at the first one it receives.
"""
from __future__ import annotations

import array
import os
import signal
import sys
import time

import rclpy
from lidar_quality_ros.qos import SENSOR_QOS
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2, PointField

TOPIC = "lq_probe/cloud"
#: 1 kB clouds sent after the probed ones (module doc)
_END_MARKERS = 3


def serialized_cloud(n_bytes: int) -> bytes:
    """A CDR PointCloud2 of x, y, z, intensity float32 points with ``n_bytes`` of data."""
    n = max(1, n_bytes // 16)
    fields = [PointField(name=f, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, f in enumerate(("x", "y", "z", "intensity"))]
    msg = PointCloud2(height=1, width=n, point_step=16, row_step=16 * n, is_dense=True,
                      fields=fields)
    msg.data = array.array("B", bytes(16 * n))
    return serialize_message(msg)


def subscribe(seconds: float) -> None:
    node = rclpy.create_node("lq_cloud_probe_sub")
    last = []

    def on_cloud(raw: bytes) -> None:
        print(f"received {len(raw)}", flush=True)
        last.append(len(raw))

    events = SubscriptionEventCallbacks(
        message_lost=lambda e: print(f"lost {e.total_count_change}", flush=True))
    node.create_subscription(PointCloud2, TOPIC, on_cloud, SENSOR_QOS, raw=True,
                             event_callbacks=events)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (last and last[-1] < 100_000):  # the end marker
        rclpy.spin_once(node, timeout_sec=0.1)
    print("done", flush=True)
    node.destroy_node()


def publish(sizes_mb: list[float], reader_pid: int) -> None:
    node = rclpy.create_node("lq_cloud_probe_pub")
    pub = node.create_publisher(PointCloud2, TOPIC,
                                QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE))
    deadline = time.monotonic() + 30.0
    while pub.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            sys.exit("cloud_probe: no subscriber matched within 30 s")
        time.sleep(0.05)
    time.sleep(0.5)
    for mb in [*sizes_mb, *[0.001] * _END_MARKERS]:
        raw = serialized_cloud(int(mb * 1e6))
        stall = mb >= 1
        if stall:
            os.kill(reader_pid, signal.SIGSTOP)
        try:
            pub.publish(raw)
            print(f"published {len(raw)}", flush=True)
            if stall:
                time.sleep(0.5)
        finally:
            if stall:
                os.kill(reader_pid, signal.SIGCONT)
        del raw
        time.sleep(1.0)
    node.destroy_node()


def main(argv: list[str]) -> None:
    rclpy.init()
    try:
        if argv[0] == "sub":
            subscribe(float(argv[1]))
        else:
            publish([float(s) for s in argv[1].split(",")], int(argv[2]))
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main(sys.argv[1:])
