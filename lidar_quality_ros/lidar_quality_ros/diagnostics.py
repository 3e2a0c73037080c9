"""Node diagnostics on ``/diagnostics`` (our small stand-in for diagnostic_updater).

Counts frames in / out / dropped (with reasons), estimates input rates, keeps recent
processing times and publishes one ``DiagnosticStatus`` per node periodically.

The level is the worst of:

* standing warnings raised by the node (``warn``; bad input, a missing input, ...). A
  warning stays visible for ``hold_s`` after it was last raised even when the next good
  frame clears it, so a problem that comes and goes between two publications still
  shows; ``warnings.<key>`` counts how often each cause was raised;
* the fraction of frames lost over the last ``window_s`` seconds (dropped by the node or
  lost by the synchroniser, against frames out): above ``drop_warn`` WARN, above
  ``drop_error`` ERROR;
* the processing time against the input period: a median frame time longer than the
  period between frames means the node cannot keep up (WARN);
* the processing time against fixed limits, when set (``processing_warn_ms`` /
  ``processing_error_ms``, as Autoware's nodes report theirs): the median of the last 50
  frames above them is WARN / ERROR.
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
                 window: int = 1000, window_s: float = 10.0, drop_warn: float = 0.05,
                 drop_error: float = 0.25, hold_s: float | None = None,
                 processing_warn_ms: float = 0.0, processing_error_ms: float = 0.0):
        self._node = node
        self.name = f"{node.get_name()}: {task}"
        self.hardware_id = node.get_fully_qualified_name()
        self._lock = threading.Lock()
        self._arrivals: dict[str, deque] = {}
        self._received: Counter = Counter()
        self._dropped: Counter = Counter()
        self._proc_ms: deque = deque(maxlen=window)
        self._warnings: dict[str, list] = {}   # key -> [message, level, raised at, cleared]
        self._warn_counts: Counter = Counter()
        self._extra: dict[str, str] = {}
        self._sources: list = []
        self.frames_out = 0
        self.window_s, self.drop_warn, self.drop_error = window_s, drop_warn, drop_error
        self.processing_warn_ms, self.processing_error_ms = processing_warn_ms, processing_error_ms
        # two publications: a problem that came and went between them is still published
        self.hold_s = max(1.0, 2.0 * period_s) if hold_s is None else hold_s
        # (monotonic time, frames out, frames lost) snapshots, from the start
        self._history: deque = deque([(time.monotonic(), 0, 0)])
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", output_qos(10))
        # Steady clock: a timer on the ROS clock under use_sim_time made rclpy's executor
        # wake between /clock messages and cost a core (measured with bag_player --clock).
        self._timer = (node.create_timer(period_s, self._tick,
                                         clock=Clock(clock_type=ClockType.STEADY_TIME))
                       if period_s > 0 else None)
        self.period_s = float(period_s) if self._timer is not None else 0.0
        #: called on each publication's tick, before it (the node's 1 Hz input check: one
        #: executor wake a second instead of two, each ~0.7 ms of CPU in rclpy)
        self.before_publish: list = []

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

    def set_values(self, items) -> None:
        """:meth:`set_value` of each ``(key, value)`` pair, under one lock (a frame's
        counts and values: ~12 of them every frame)."""
        with self._lock:
            for key, value in items:
                self._extra[key] = str(value)

    def add_source(self, values_fn, dropped_fn=None, frames_lost_fn=None) -> None:
        """Add a callable returning extra ``{key: value}`` items at each publication, and
        optionally one returning a count of input messages it lost (added to ``dropped``)
        and one estimating the frames those messages were (for the drop fraction; default
        ``dropped_fn``)."""
        with self._lock:
            self._sources.append((values_fn, dropped_fn, frames_lost_fn or dropped_fn))

    def warn(self, key: str, message: str, level: int = WARN, *, transient: bool = False) -> None:
        """Raise a standing warning (shown until ``clear``, and at least ``hold_s``); a
        ``transient`` one (an event, e.g. one undecodable message) is shown for ``hold_s``."""
        with self._lock:
            self._warnings[key] = [message, level, time.monotonic(), transient]
            self._warn_counts[key] += 1

    def clear(self, key: str) -> None:
        with self._lock:
            w = self._warnings.get(key)
            if w is not None:
                w[3] = True

    def warning_keys(self) -> set[str]:
        """Keys of the warnings currently shown."""
        with self._lock:
            return set(self._current_warnings())

    def _current_warnings(self) -> dict[str, list]:
        now = time.monotonic()
        for key in [k for k, w in self._warnings.items() if w[3] and now - w[2] >= self.hold_s]:
            del self._warnings[key]
        return self._warnings

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
        return own + sum(d() for _, d, _ in sources if d is not None)

    def health(self, frames_lost_upstream: int = 0) -> tuple[int, list[str], dict]:
        """``(level, messages, values)`` of the drop fraction over the window and the
        processing time against the input period."""
        now = time.monotonic()
        with self._lock:
            lost = sum(self._dropped.values()) + frames_lost_upstream
            h = self._history
            h.append((now, self.frames_out, lost))
            while len(h) > 2 and now - h[1][0] >= self.window_s:
                h.popleft()
            t0, out0, lost0 = h[0]
            d_out, d_lost = self.frames_out - out0, lost - lost0
            recent = list(self._proc_ms)[-50:]
            arrivals = [a for a in self._arrivals.values() if len(a) > 1]
        level, msgs, values = OK, [], {}
        if d_out + d_lost > 0:
            frac = d_lost / (d_out + d_lost)
            values["dropped_fraction_window"] = f"{frac:.3f}"
            if frac > self.drop_warn:
                # a few frames are too few to call an error (one bad frame of one is 100 %)
                level = ERROR if frac > self.drop_error and d_out + d_lost >= 10 else WARN
                msgs.append(f"{d_lost} of {d_out + d_lost} frames lost in the last "
                            f"{now - t0:.0f} s ({100 * frac:.0f} %)")
        # the input period: the slowest input's (every frame needs one of each)
        periods = [(a[-1] - a[0]) / (len(a) - 1) for a in arrivals
                   if now - a[-1] < 5.0 and a[-1] > a[0]]
        if periods and len(recent) >= 5:
            period_ms = 1e3 * max(periods)
            proc = float(np.median(recent))
            values["input_period_ms"] = f"{period_ms:.1f}"
            if proc > period_ms:
                level = max(level, WARN)
                msgs.append(f"processing takes {proc:.0f} ms per frame (median), longer than "
                            f"the input period {period_ms:.0f} ms: the node cannot keep up")
        if recent and (self.processing_warn_ms > 0 or self.processing_error_ms > 0):
            proc = float(np.median(recent))
            values["processing_ms_recent"] = f"{proc:.3f}"
            for limit, lvl, name in ((self.processing_error_ms, ERROR, "processing_error_ms"),
                                     (self.processing_warn_ms, WARN, "processing_warn_ms")):
                if 0 < limit < proc:
                    level = max(level, lvl)
                    msgs.append(f"processing takes {proc:.1f} ms per frame (median of the "
                                f"last {len(recent)}), above {name} = {limit:g} ms")
                    break
        return level, msgs, values

    def status(self) -> DiagnosticStatus:
        with self._lock:
            sources = list(self._sources)
        extra, upstream, lost_frames = {}, 0, 0
        for values_fn, dropped_fn, lost_fn in sources:  # outside our lock: they take their own
            extra.update(values_fn())
            upstream += dropped_fn() if dropped_fn is not None else 0
            lost_frames += lost_fn() if lost_fn is not None else 0
        h_level, h_msgs, h_values = self.health(lost_frames)
        extra.update(h_values)
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
            extra.update((f"warnings.{k}", n) for k, n in self._warn_counts.items())
            values += [KeyValue(key=k, value=str(v)) for k, v in sorted(extra.items())]
            warnings = self._current_warnings()
            levels = [w[1] for w in warnings.values()] + [h_level]
            texts = [w[0] for w in sorted(warnings.values(), key=lambda w: w[1], reverse=True)] + h_msgs
        level = max(levels)
        message = "; ".join(texts) if texts else "ok"
        return DiagnosticStatus(level=level, name=self.name, message=message,
                                hardware_id=self.hardware_id, values=values)

    def _tick(self) -> None:
        try:
            for fn in self.before_publish:
                fn()
        finally:  # a failing hook still raises, after the publication
            self.publish()

    def publish(self) -> None:
        msg = DiagnosticArray(status=[self.status()])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)
