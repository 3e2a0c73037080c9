"""``lms_node``: the LidarMetaSeg node shell.

Subscribes to ``input/points`` (a cloud with per-point class probabilities), decodes and
validates it and republishes it on ``output/points``. Segment metrics and meta models
are not in this node yet: until they are, the cloud passes through unchanged.
"""
from __future__ import annotations

import time

from lidar_quality_core.pointcloud import CloudFormatError, xyz_intensity
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2


class LmsNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("lms_node", **kwargs)
        self.pub_points = self.create_publisher(PointCloud2, "output/points", output_qos(5))
        self.inputs = SyncedInputs(self, [(PointCloud2, "input/points")], self.on_frame,
                                   diagnostics=self.diag, **self.declare_sync_parameters())
        self.get_logger().info(f"lms_node ready, inputs: {', '.join(self.inputs.topics)}")

    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        cloud = synced.messages[0]
        try:
            xyz_intensity(cloud)
        except CloudFormatError as exc:
            self.warn_input("cloud", f"dropping frame: malformed input/points: {exc}")
            self.diag.frame_dropped("malformed_cloud")
            return
        self.diag.clear("cloud")
        self.pub_points.publish(cloud)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(LmsNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
