"""The shell the reference nodes share: ``input/points`` decoded into a CloudInput, then
the node's ``process`` (malformed clouds dropped with a warning and counted)."""
from __future__ import annotations

import time

from lidar_quality_core.pointcloud import CloudFormatError
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2

from .cloud_input import CloudInput, read_cloud


class CloudNode(QualityNode):
    """Subclasses create their publishers, call :meth:`subscribe_points` last and implement
    :meth:`process`."""

    def subscribe_points(self) -> None:
        self.inputs = SyncedInputs(self, [(PointCloud2, "input/points")], self._on_frame,
                                   diagnostics=self.diag, **self.declare_sync_parameters())

    def process(self, header, cloud: CloudInput) -> None:
        raise NotImplementedError

    def _on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        msg = synced.messages[0]
        try:
            cloud = read_cloud(msg)
        except CloudFormatError as exc:
            self.warn_input("cloud", f"dropping frame: malformed input/points: {exc}")
            self.diag.frame_dropped("malformed_cloud")
            return
        self.diag.clear("cloud")
        self.process(msg.header, cloud)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)
