"""rosbag2 files as rclpy messages, via the ``rosbags`` library (no rosbag2 needed).

Messages are (de)serialised by rclpy itself (``rclpy.serialization``), so the objects read
and written are exactly the ones nodes publish and receive; messages that are only copied
keep their original bytes. Our own message packages are registered in the ``rosbags``
typestore from their .msg files (:mod:`lidar_quality_core.rosbag_types`), so the bags carry
the definitions ``ros2 bag`` and Foxglove need.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from lidar_quality_core.rosbag_types import typestore

STORAGES = ("mcap", "sqlite3")


def message_class(msgtype: str):
    """rclpy message class of ``pkg/msg/Name``."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    stamp_ns: int       # log time
    raw: bytes

    def decode(self):
        """The rclpy message."""
        from rclpy.serialization import deserialize_message

        return deserialize_message(self.raw, message_class(self.msgtype))


def bag_topics(path: Path | str) -> dict[str, str]:
    """Topic -> message type of a bag."""
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as r:
        return {c.topic: c.msgtype for c in r.connections}


def read_bag(path: Path | str, topics=None, *, start_ns: int | None = None) -> Iterator[BagMessage]:
    """Messages of a bag (optionally only ``topics``, only from log time ``start_ns``) in
    log-time order."""
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as r:
        conns = [c for c in r.connections if topics is None or c.topic in topics]
        if not conns:  # rosbags reads every topic when given no connection
            return
        for conn, stamp, raw in r.messages(connections=conns, start=start_ns):
            yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(raw))


@dataclass
class TopicInfo:
    msgtype: str
    count: int
    qos: list           # offered QoS profiles of metadata.yaml (rclpy QoSProfile), may be empty


@dataclass
class BagInfo:
    start_ns: int       # first log time
    end_ns: int         # last log time
    topics: dict[str, TopicInfo]


def bag_info(path: Path | str) -> BagInfo:
    """Time span, topics, message counts and recorded QoS of a bag."""
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as r:
        topics = {c.topic: TopicInfo(c.msgtype, c.msgcount,
                                     [_qos_to_rclpy(q) for q in c.ext.offered_qos_profiles])
                  for c in r.connections}
        if not r.message_count:
            return BagInfo(0, 0, topics)
        return BagInfo(r.start_time, r.end_time - 1, topics)  # rosbags' end_time is exclusive


def _qos_to_rclpy(q):
    # rosbags' QoS enums have the rmw values, as rclpy's policies do
    from rclpy.duration import Duration
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                           ReliabilityPolicy)

    def dur(t):
        return Duration(seconds=t.sec, nanoseconds=t.nsec)

    return QoSProfile(history=HistoryPolicy(q.history.value), depth=q.depth,
                      reliability=ReliabilityPolicy(q.reliability.value),
                      durability=DurabilityPolicy(q.durability.value),
                      deadline=dur(q.deadline), lifespan=dur(q.lifespan),
                      liveliness=LivelinessPolicy(q.liveliness.value),
                      liveliness_lease_duration=dur(q.liveliness_lease_duration),
                      avoid_ros_namespace_conventions=q.avoid_ros_namespace_conventions)


def _qos_from_rclpy(p):
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    def t(d):
        sec, nsec = divmod(d.nanoseconds, 10**9)
        return QosTime(sec, nsec)

    return Qos(QosHistory(int(p.history)), p.depth, QosReliability(int(p.reliability)),
               QosDurability(int(p.durability)), t(p.deadline), t(p.lifespan),
               QosLiveliness(int(p.liveliness)), t(p.liveliness_lease_duration),
               p.avoid_ros_namespace_conventions)


class BagWriter:
    """Writes rclpy messages (or raw CDR bytes) to a new rosbag2 (format version 9)."""

    def __init__(self, path: Path | str, *, storage: str = "mcap"):
        from rosbags.rosbag2 import StoragePlugin, Writer

        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
        self._writer = Writer(Path(path), version=9, storage_plugin=plugin)
        self._ts = typestore()
        self._conns: dict[str, object] = {}

    def __enter__(self):
        self._writer.open()
        return self

    def __exit__(self, *exc):
        self._writer.close()

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg, *, qos=()) -> None:
        """Write ``msg`` (an rclpy message, or bytes already serialised) on ``topic``;
        ``qos`` (rclpy QoSProfiles, taken at a topic's first message) are recorded as
        its offered QoS profiles."""
        from rclpy.serialization import serialize_message

        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self._ts,
                offered_qos_profiles=[_qos_from_rclpy(p) for p in qos])
        raw = msg if isinstance(msg, (bytes, bytearray, memoryview)) else serialize_message(msg)
        self._writer.write(conn, int(stamp_ns), bytes(raw))
