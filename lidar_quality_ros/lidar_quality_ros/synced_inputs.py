"""Stamp-synchronised subscriptions (our stand-in for message_filters).

Each input gets a subscription in a reentrant callback group; arrivals go through
``lidar_quality_core.time_sync.StampSynchronizer`` and the user callback runs on the
matched set after the synchroniser released its lock, so a long frame never blocks the
subscriptions of the next one.
"""
from __future__ import annotations

import traceback
from typing import Callable, Sequence

from lidar_quality_core.time_sync import StampSynchronizer, SyncedSet, stamp_to_ns
from rclpy.callback_groups import ReentrantCallbackGroup

from .qos import SENSOR_QOS


class SyncedInputs:
    """Subscribe to ``topics`` (list of ``(msg_type, topic)``) and call ``callback(set)``."""

    def __init__(self, node, topics: Sequence[tuple[type, str]],
                 callback: Callable[[SyncedSet], None], *, mode: str = "exact",
                 slop_s: float = 0.0, queue_size: int = 10, qos=SENSOR_QOS, diagnostics=None):
        self.topics = [t for _, t in topics]
        self.sync = StampSynchronizer(len(topics), mode=mode,
                                      slop_ns=int(round(slop_s * 1e9)) if mode == "approximate" else 0,
                                      queue_size=queue_size)
        self._callback = callback
        self._diag = diagnostics
        self._logger = node.get_logger()
        self._group = ReentrantCallbackGroup()
        self.subscriptions = [
            node.create_subscription(msg_type, topic, self._make_cb(i), qos,
                                     callback_group=self._group)
            for i, (msg_type, topic) in enumerate(topics)
        ]
        if diagnostics is not None:
            diagnostics.add_source(self._stats, self.unmatched_dropped)

    def _make_cb(self, index: int):
        topic = self.topics[index]

        def on_message(msg) -> None:
            if self._diag is not None:
                self._diag.input_received(topic)
            stamp = msg.header.stamp
            for matched in self.sync.add(index, stamp_to_ns(stamp.sec, stamp.nanosec), msg):
                self._run(matched)
        return on_message

    def _run(self, matched: SyncedSet) -> None:
        # A bug or an unforeseen input must cost one frame, never the node.
        try:
            self._callback(matched)
        except Exception as exc:  # noqa: BLE001
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
