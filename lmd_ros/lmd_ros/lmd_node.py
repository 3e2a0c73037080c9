"""``lmd_node``: the LidarMetaDetect node shell.

Subscribes to ``input/points`` and ``input/detections`` (optionally ``input/proposals``),
matches them by stamp, decodes and validates cloud and boxes and republishes the
detections on ``output/detections``. The box-wise features and meta models are not in
this node yet: until they are, detections pass through unchanged (same order, ids and
scores).
"""
from __future__ import annotations

import time

from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.pointcloud import CloudFormatError, xyz_intensity
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray


class LmdNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("lmd_node", **kwargs)
        self.use_proposals = declare(
            self, "use_proposals", False,
            "Also subscribe to input/proposals (pre-NMS Detection3DArray, same stamps).")
        topics = [(PointCloud2, "input/points"), (Detection3DArray, "input/detections")]
        if self.use_proposals:
            topics.append((Detection3DArray, "input/proposals"))
        self.pub_detections = self.create_publisher(Detection3DArray, "output/detections",
                                                    output_qos())
        self.inputs = SyncedInputs(self, topics, self.on_frame, diagnostics=self.diag,
                                   **self.declare_sync_parameters())
        self.get_logger().info(f"lmd_node ready, inputs: {', '.join(self.inputs.topics)}")

    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        cloud, detections = synced.messages[0], synced.messages[1]
        try:
            xyz_intensity(cloud)
        except CloudFormatError as exc:
            self.warn_input("cloud", f"dropping frame: malformed input/points: {exc}")
            self.diag.frame_dropped("malformed_cloud")
            return
        self.diag.clear("cloud")
        arrays = detections_to_arrays(detections)
        if not arrays.valid.all():
            bad = [f"#{i}: {r}" for i, r in enumerate(arrays.reasons) if r]
            self.warn_input("detections", f"{len(bad)} invalid detection(s): {', '.join(bad[:5])}")
        else:
            self.diag.clear("detections")
        self.pub_detections.publish(detections)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(LmdNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
