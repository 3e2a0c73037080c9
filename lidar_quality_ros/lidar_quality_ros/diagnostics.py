"""Node diagnostics on ``/diagnostics`` (our small stand-in for diagnostic_updater).

Counts frames in / out / dropped (with reasons), estimates input rates, keeps recent
processing times and publishes one ``DiagnosticStatus`` per node periodically.
"""
from __future__ import annotations

import threading
import time
from collections import Counter, deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType

from .qos import output_qos

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


class NodeDiagnostics:
    """Thread-safe counters of one node, published every ``period_s`` seconds."""

    def __init__(self, node, task: str = "processing", *, period_s: float = 1.0,
                 window: int = 1000):
        self._node = node
        self.name = f"{node.get_name()}: {task}"
        self.hardware_id = node.get_fully_qualified_name()
        self._lock = threading.Lock()
        self._arrivals: dict[str, deque] = {}
        self._received: Counter = Counter()
        self._dropped: Counter = Counter()
        self._proc_ms: deque = deque(maxlen=window)
        self._warnings: dict[str, str] = {}
        self._extra: dict[str, str] = {}
        self._sources: list = []
        self.frames_out = 0
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", output_qos(10))
        # Steady clock: a timer on the ROS clock under use_sim_time made rclpy's executor
        # wake between /clock messages and cost a core (measured with bag_player --clock).
        self._timer = (node.create_timer(period_s, self.publish,
                                         clock=Clock(clock_type=ClockType.STEADY_TIME))
                       if period_s > 0 else None)

    def input_received(self, topic: str) -> None:
        with self._lock:
            self._received[topic] += 1
            self._arrivals.setdefault(topic, deque(maxlen=50)).append(time.monotonic())

    def frame_processed(self, processing_ms: float) -> None:
        with self._lock:
            self.frames_out += 1
            self._proc_ms.append(processing_ms)

    def frame_dropped(self, reason: str, n: int = 1) -> None:
        with self._lock:
            self._dropped[reason] += n

    def set_value(self, key: str, value) -> None:
        with self._lock:
            self._extra[key] = str(value)

    def add_source(self, values_fn, dropped_fn=None) -> None:
        """Add a callable returning extra ``{key: value}`` items at each publication, and
        optionally one returning a count of input messages it lost (added to ``dropped``)."""
        with self._lock:
            self._sources.append((values_fn, dropped_fn))

    def warn(self, key: str, message: str) -> None:
        """Raise a standing warning (shown until ``clear``)."""
        with self._lock:
            self._warnings[key] = message

    def clear(self, key: str) -> None:
        with self._lock:
            self._warnings.pop(key, None)

    def counts(self) -> dict[str, int]:
        """Cheap snapshot of the node's own counters: ``frames_out``,
        ``received.<topic>`` and ``dropped.<reason>`` (no sources, no percentiles)."""
        with self._lock:
            out = {"frames_out": self.frames_out}
            out.update((f"received.{t}", n) for t, n in self._received.items())
            out.update((f"dropped.{r}", n) for r, n in self._dropped.items())
        return out

    @property
    def dropped(self) -> int:
        """Frames dropped by the node plus input messages lost upstream (synchroniser)."""
        with self._lock:
            own, sources = sum(self._dropped.values()), list(self._sources)
        return own + sum(d() for _, d in sources if d is not None)

    def status(self) -> DiagnosticStatus:
        with self._lock:
            sources = list(self._sources)
        extra, upstream = {}, 0
        for values_fn, dropped_fn in sources:  # outside our lock: sources take their own
            extra.update(values_fn())
            upstream += dropped_fn() if dropped_fn is not None else 0
        with self._lock:
            values = [KeyValue(key="frames_out", value=str(self.frames_out)),
                      KeyValue(key="dropped", value=str(sum(self._dropped.values()) + upstream))]
            values += [KeyValue(key=f"dropped.{r}", value=str(n)) for r, n in sorted(self._dropped.items())]
            for topic, n in sorted(self._received.items()):
                values.append(KeyValue(key=f"received.{topic}", value=str(n)))
                t = self._arrivals[topic]
                rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
                if t and time.monotonic() - t[-1] > 5.0:
                    rate = 0.0
                values.append(KeyValue(key=f"rate_hz.{topic}", value=f"{rate:.2f}"))
            if self._proc_ms:
                p = np.percentile(np.fromiter(self._proc_ms, float), [50, 99])
                values += [KeyValue(key="processing_ms_p50", value=f"{p[0]:.3f}"),
                           KeyValue(key="processing_ms_p99", value=f"{p[1]:.3f}")]
            extra.update(self._extra)
            values += [KeyValue(key=k, value=str(v)) for k, v in sorted(extra.items())]
            level, message = (WARN, "; ".join(self._warnings.values())) if self._warnings else (OK, "ok")
        return DiagnosticStatus(level=level, name=self.name, message=message,
                                hardware_id=self.hardware_id, values=values)

    def publish(self) -> None:
        msg = DiagnosticArray(status=[self.status()])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)
