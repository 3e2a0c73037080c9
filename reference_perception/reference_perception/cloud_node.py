"""The shell the reference nodes share: ``input/points`` decoded into a CloudInput, then
the node's :meth:`CloudNode.process_cloud` (the frame contract of ``QualityNode``: a
malformed cloud is dropped with a warning and counted)."""
from __future__ import annotations

from lidar_quality_ros.node_base import QualityNode
from sensor_msgs.msg import PointCloud2

from .cloud_input import CloudInput, read_cloud


class CloudNode(QualityNode):
    """Subclasses create their outputs (``create_output``), call :meth:`subscribe_points`
    last and implement :meth:`process_cloud`."""

    def subscribe_points(self) -> None:
        self.start_inputs([(PointCloud2, "input/points")])

    def process_cloud(self, header, cloud: CloudInput):
        """One decoded cloud -> ``lidar_quality_core.frame.FrameOutputs``."""
        raise NotImplementedError

    def process(self, messages: list, markers: bool):
        return self.process_cloud(messages[0].header, read_cloud(messages[0]))
