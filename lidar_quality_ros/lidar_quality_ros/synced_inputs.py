"""Stamp-synchronised subscriptions (our stand-in for message_filters).

Each input gets a subscription; arrivals go through
``lidar_quality_core.time_sync.StampSynchronizer``. Matched sets are handed to one
worker thread that runs the user callback on them one at a time, in the order they were
matched: subscriptions never wait for a long frame (no lock is held while the callback
runs), outputs stay in input order, and a node that falls behind drops the oldest
waiting frame (counted as ``overrun``) instead of building up latency.
"""
from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from typing import Callable, Sequence

from lidar_quality_core.input_watchdog import InputWatchdog
from lidar_quality_core.time_sync import StampSynchronizer, SyncedSet, stamp_to_ns
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks

from .qos import SENSOR_QOS


class OrderedWorker:
    """Runs ``fn(item)`` on a thread of its own, in submission order, keeping at most
    ``max_pending`` items waiting; ``on_overrun(n)`` hears of the items it discarded."""

    def __init__(self, fn: Callable, max_pending: int, on_overrun: Callable[[int], None],
                 name: str = "lq_frame_worker"):
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        self._fn, self._max, self._on_overrun = fn, max_pending, on_overrun
        self._pending: deque = deque()
        self._cond = threading.Condition()
        self._stopping = False
        self._busy = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(self, item) -> None:
        with self._cond:
            if self._stopping:
                return
            discarded = 0
            while len(self._pending) >= self._max:
                self._pending.popleft()
                discarded += 1
            self._pending.append(item)
            self._cond.notify()
        if discarded:
            self._on_overrun(discarded)

    def idle(self) -> bool:
        with self._cond:
            return not self._pending and not self._busy

    def _loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._stopping)
                if not self._pending:
                    return
                item = self._pending.popleft()
                self._busy = True
            try:
                self._fn(item)
            finally:
                with self._cond:
                    self._busy = False

    def stop(self, timeout: float = 5.0) -> None:
        """Finish the item being processed, discard the waiting ones, end the thread."""
        with self._cond:
            self._stopping = True
            self._pending.clear()
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)


class SyncedInputs:
    """Subscribe to ``topics`` (list of ``(msg_type, topic)``) and call ``callback(set)``
    for every matched set, on the worker thread, in matching order.

    ``on_arrival(index, stamp_ns)``, if given, hears of every message before it is
    matched; with :meth:`inject` a node can stand in for an input that stopped (e.g.
    ``None`` messages, so the other inputs' sets still complete).

    ``raw_decoders`` maps topics to ``fn(bytes) -> obj with .header.stamp``: those are
    subscribed with ``raw=True`` and decoded on arrival (messages rclpy would deserialize
    far too slowly, e.g. ``detection_cdr.decode_detection_array``); bytes that do not
    decode are dropped and counted (``undecodable_input``).

    ``watchdog`` (an ``InputWatchdog`` over the same inputs) hears of every arrival and
    every matched set, so the node can tell why nothing comes out."""

    def __init__(self, node, topics: Sequence[tuple[type, str]],
                 callback: Callable[[SyncedSet], None], *, mode: str = "exact",
                 slop_s: float = 0.0, queue_size: int = 10, processing_queue_size: int = 2,
                 qos=SENSOR_QOS, diagnostics=None,
                 on_arrival: Callable[[int, int], None] | None = None,
                 raw_decoders: dict[str, Callable[[bytes], object]] | None = None,
                 watchdog: InputWatchdog | None = None):
        self.topics = [t for _, t in topics]
        self.watchdog = watchdog
        self._decoders = dict(raw_decoders or {})
        self._on_arrival = on_arrival
        self.sync = StampSynchronizer(len(topics), mode=mode,
                                      slop_ns=int(round(slop_s * 1e9)) if mode == "approximate" else 0,
                                      queue_size=queue_size)
        self._callback = callback
        self._diag = diagnostics
        self._logger = node.get_logger()
        self.worker = OrderedWorker(self._run, processing_queue_size, self._overrun,
                                    name=f"{node.get_name()}_frames")
        self._group = ReentrantCallbackGroup()
        self._warn = getattr(node, "warn_input", None)
        self.subscriptions = [
            node.create_subscription(
                msg_type, topic, self._make_cb(i), qos, callback_group=self._group,
                raw=topic in self._decoders,
                event_callbacks=SubscriptionEventCallbacks(message_lost=self._make_lost_cb(i)))
            for i, (msg_type, topic) in enumerate(topics)
        ]
        if diagnostics is not None:
            diagnostics.add_source(self._stats, self.unmatched_dropped, self.frames_lost)

    def _make_cb(self, index: int):
        topic = self.topics[index]
        decode = self._decoders.get(topic)

        def on_message(msg) -> None:
            if self._diag is not None:
                self._diag.input_received(topic)
            if decode is not None:
                try:
                    msg = decode(msg)
                except Exception as exc:  # noqa: BLE001 - bad bytes cost this message only
                    self._dropped("undecodable_input", f"undecodable.{topic}",
                                  f"dropping a message on {topic}: cannot decode it: {exc}")
                    return
            stamp = msg.header.stamp
            try:
                stamp_ns = stamp_to_ns(stamp.sec, stamp.nanosec)
            except ValueError as exc:
                # nanosec >= 1e9 passes the wire (uint32): it must cost this message, not
                # the node (an exception here stops the executor; found by fuzzing).
                self._dropped("invalid_stamp", f"invalid_stamp.{topic}",
                              f"dropping a message on {topic}: {exc}")
                return
            if self.watchdog is not None:
                self.watchdog.arrival(index, stamp_ns, time.monotonic())
            if self._on_arrival is not None:
                self._on_arrival(index, stamp_ns)
            self.inject(index, stamp_ns, msg)
        return on_message

    def _make_lost_cb(self, index: int):
        topic = self.topics[index]

        def on_lost(info) -> None:
            # the middleware lost messages before they reached us (e.g. a cloud larger than
            # the DDS profile carries): without this they would be counted nowhere
            n = int(info.total_count_change)
            text = (f"{info.total_count} message(s) on {topic} lost in transport before they "
                    "reached the node (a cloud larger than the shared-memory profile carries? "
                    "see LQ_SHM_SEGMENT_MB in the README)")
            self._dropped("message_lost", f"lost.{topic}", text, n)
        return on_lost

    def _dropped(self, reason: str, cause: str, text: str, n: int = 1):
        """Count ``n`` dropped under ``reason`` and warn under ``cause``: through the node's
        per-cause warnings (shown in /diagnostics for their hold time) when it has them."""
        if self._diag is not None:
            self._diag.frame_dropped(reason, n)
        if self._warn is not None:
            self._warn(cause, text, transient=True)
        else:
            self._logger.warn(text, throttle_duration_sec=5.0)

    def inject(self, index: int, stamp_ns: int, msg) -> None:
        """Queue ``msg`` for input ``index`` at ``stamp_ns`` as if it had arrived (not
        counted as received in the diagnostics) and process the set it completes."""
        for matched in self.sync.add(index, stamp_ns, msg):
            if self.watchdog is not None:
                self.watchdog.matched(time.monotonic())
            self.worker.submit(matched)

    def _overrun(self, n: int) -> None:
        self._dropped("overrun", "overrun",
                      f"processing falls behind the input: dropped {n} waiting frame(s)", n)

    def _run(self, matched: SyncedSet) -> None:
        # A bug or an unforeseen input must cost one frame, never the node.
        try:
            self._callback(matched)
        except Exception as exc:  # noqa: BLE001 - a bug or bad input costs this frame only
            # the traceback in the log; /diagnostics keeps the one-line cause
            self._logger.error(f"frame at stamp {matched.stamp_ns} ns dropped: "
                               f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}",
                               throttle_duration_sec=5.0)
            if self._diag is not None:
                self._diag.frame_dropped("processing_error")
                self._diag.warn("processing_error", f"processing error: {type(exc).__name__}: {exc}")

    def _stats(self) -> dict[str, str]:
        s = self.sync.stats()
        out = {"sync.matched": str(s.matched), "sync.resets": str(s.resets)}
        for i, topic in enumerate(self.topics):
            out[f"sync.late.{topic}"] = str(s.late[i])
            out[f"sync.dropped.{topic}"] = str(s.dropped[i])
        return out

    def unmatched_dropped(self) -> int:
        """Input messages lost by the synchroniser (late, overflow, unmatched, reset)."""
        s = self.sync.stats()
        return sum(s.dropped) + sum(s.late)

    def frames_lost(self) -> int:
        """Frames the synchroniser lost, estimated as the most messages lost on one input
        (a frame lost on every input is one frame, not one per input)."""
        s = self.sync.stats()
        return max(d + late for d, late in zip(s.dropped, s.late))

    def close(self) -> None:
        self.worker.stop()
