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


def read_bag(path: Path | str, topics=None) -> Iterator[BagMessage]:
    """Messages of a bag (optionally only ``topics``) in log-time order."""
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as r:
        conns = [c for c in r.connections if topics is None or c.topic in topics]
        for conn, stamp, raw in r.messages(connections=conns):
            yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(raw))


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

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg) -> None:
        """Write ``msg`` (an rclpy message, or bytes already serialised) on ``topic``."""
        from rclpy.serialization import serialize_message

        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._ts)
        raw = msg if isinstance(msg, (bytes, bytearray, memoryview)) else serialize_message(msg)
        self._writer.write(conn, int(stamp_ns), bytes(raw))
