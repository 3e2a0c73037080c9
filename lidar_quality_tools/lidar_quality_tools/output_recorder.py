"""The load test's receiving end, as a process of its own (``LoadTest``).

Subscribes raw to the given topics and writes one line per message to stdout:
``r <name> <stamp ns> <time.monotonic()>`` (the clock is the system's CLOCK_MONOTONIC, the
same in every process), ``m <name>`` once a topic has a publisher, and once at start
``s <scheduling>``: what its threads run with (``normal``, ``SCHED_FIFO <p>``, or
``normal (refused: <why>)``).

Why a process: in the publishing process an rclpy ``publish`` of a large cloud holds the
GIL for the whole call (measured: an 8.6 MB LMS cloud, 1.8 ms quiet and 8-14 ms with the
three nodes running; a thread spinning beside it stalls for exactly that long), so a
receiving callback there waited for the LMS publication and every LMD and MIMO output that
arrived meanwhile was stamped late by up to that much. A consumer of the nodes' outputs in
a real stack does not share the lidar driver's interpreter.

Why ``--realtime-priority P`` (SCHED_FIFO for all of its threads, as a node's
``realtime_priority``): the recorder stands for the consumer of the outputs. On two cores a
consumer at normal priority waits for a core behind LMD's and LMS's frames and the cloud
publications, and that wait, not the node's, made most of MIMO's tail (alternating 40-s
load tests, MIMO at FIFO 10, 2026-12-01: p99 11.8 / 11.7 ms with the recorder at normal
priority, 8.4 / 8.0 with it at FIFO 10; LMD's and LMS's figures unchanged). A deployment
that gives a node real-time priority for its latency gives it to the node's consumer too,
or the priority buys nothing end to end.

Usage: ``python -m lidar_quality_tools.output_recorder [--realtime-priority P] NAME TOPIC
TYPE [NAME TOPIC TYPE ...]`` (``TYPE`` as ``pkg/msg/Name``); it runs until SIGINT / SIGTERM
or until its stdin closes.
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
import threading
import time


def _message_class(type_name: str):
    """Message class of a ROS type name ``pkg/msg/Name``."""
    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def parse_line(line: str):
    """``("r", name, stamp_ns, t)``, ``("m", name)``, ``("s", scheduling)`` or None for a
    line of the recorder."""
    parts = line.split()
    if len(parts) == 4 and parts[0] == "r":
        return "r", parts[1], int(parts[2]), float(parts[3])
    if len(parts) == 2 and parts[0] == "m":
        return "m", parts[1]
    if len(parts) >= 2 and parts[0] == "s":
        return "s", line.strip()[2:]
    return None


def main(argv: list[str] | None = None) -> int:
    import rclpy
    from lidar_quality_core.time_sync import stamp_of_bytes
    from lidar_quality_ros.qos import output_qos
    from lidar_quality_ros.threads import realtime_scheduling
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    args = list(sys.argv[1:] if argv is None else argv)
    priority = 0
    if args[:1] == ["--realtime-priority"] and len(args) > 1 and args[1].isdigit():
        priority, args = int(args[1]), args[2:]
    if not args or len(args) % 3:
        print(__doc__, file=sys.stderr)
        return 2
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"lq_output_recorder_{os.getpid()}")
    out = sys.stdout.fileno()

    def writer(name: str):
        def on_message(data: bytes) -> None:
            now = time.monotonic()  # first: the reception time is what is measured
            os.write(out, f"r {name} {stamp_of_bytes(data)} {now!r}\n".encode())
        return on_message

    subs = {}
    for name, topic, type_name in zip(args[0::3], args[1::3], args[2::3]):
        subs[name] = node.create_subscription(_message_class(type_name), topic, writer(name),
                                              output_qos(50), raw=True)
    unmatched = dict(subs)
    # after the subscriptions: rclpy's and Fast DDS's threads exist, later ones inherit it
    scheduling = "normal"
    if priority > 0:
        _, refused = realtime_scheduling(priority)
        scheduling = f"normal (refused: {refused})" if refused else f"SCHED_FIFO {priority}"
    os.write(out, f"s {scheduling}\n".encode())

    def report_matches() -> None:
        for name, sub in list(unmatched.items()):
            if sub.get_publisher_count() > 0:
                os.write(out, f"m {name}\n".encode())
                del unmatched[name]
    node.create_timer(0.05, report_matches)

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def watch_stdin() -> None:  # the load test went away: so do we
        try:  # the raw descriptor: a buffered reader's lock held here aborts the exit
            while os.read(0, 4096):
                pass
        except OSError:
            pass
        finally:
            stop.set()
    threading.Thread(target=watch_stdin, daemon=True).start()

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    executor.remove_node(node)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
