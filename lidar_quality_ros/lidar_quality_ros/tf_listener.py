"""``/tf_static`` and ``/tf`` into a :class:`lidar_quality_core.transforms.TransformBuffer`.

The subscriptions use tf2's QoS (``tf2_ros.StaticListenerQoS`` / ``DynamicListenerQoS``):
reliable, depth 100, and transient local for ``/tf_static``, so the static transforms
published before the node started still arrive. ``tf2_msgs`` comes from the system (with
/opt/ros/jazzy) or from the workspace's rebuild of its messages (``ros2_ws/src/tf2_msgs``,
the PyPI wheels have none); ``tf2_ros`` is not needed. Entries that cannot be used (a zero
quaternion, NaN, a frame that is its own parent) are passed to ``on_bad`` (the node warns).
"""
from __future__ import annotations

from typing import Callable

from lidar_quality_core.transforms import TransformBuffer, add_tf_message
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

__all__ = ["TfListener", "tf_qos", "tf_static_qos"]


def tf_qos() -> QoSProfile:
    """tf2's DynamicListenerQoS: reliable, volatile, keep last 100."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def tf_static_qos() -> QoSProfile:
    """tf2's StaticListenerQoS: reliable, transient local, keep last 100."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


class TfListener:
    """Fills ``buffer`` (a new one if None) from ``/tf_static`` and ``/tf`` of ``node``.

    ``on_bad(text)``: called for each transform that was refused. The callbacks run in
    their own callback group, so a long frame does not hold them up in a multi-threaded
    executor."""

    def __init__(self, node, buffer: TransformBuffer | None = None, *,
                 on_bad: Callable[[str], None] | None = None,
                 static_topic: str = "/tf_static", topic: str = "/tf"):
        self.buffer = buffer if buffer is not None else TransformBuffer()
        self.on_bad = on_bad
        self.received = {"static": 0, "dynamic": 0}
        group = MutuallyExclusiveCallbackGroup()
        self._node = node
        self.subscriptions = [
            node.create_subscription(TFMessage, static_topic, self._on_static, tf_static_qos(),
                                     callback_group=group),
            node.create_subscription(TFMessage, topic, self._on_dynamic, tf_qos(),
                                     callback_group=group)]

    def _add(self, msg, static: bool) -> None:
        self.received["static" if static else "dynamic"] += len(msg.transforms)
        bad = add_tf_message(self.buffer, msg, static)
        if bad and self.on_bad is not None:
            self.on_bad(f"{len(bad)} transform(s) on {'/tf_static' if static else '/tf'} "
                        "refused: " + "; ".join(bad[:3]))

    def _on_static(self, msg) -> None:
        self._add(msg, True)

    def _on_dynamic(self, msg) -> None:
        self._add(msg, False)

    def destroy(self) -> None:
        for s in self.subscriptions:
            self._node.destroy_subscription(s)
        self.subscriptions = []
