"""``detector_node``: the reference 3D detector as a ROS 2 node.

Subscribes to ``input/points`` (PointCloud2) and publishes ``output/detections`` (post-NMS
Detection3DArray) and ``output/proposals`` (pre-NMS Detection3DArray), both with the
cloud's header. Each detection carries the class distribution as hypotheses and the id of
the proposal it came from (see :mod:`reference_perception.messages`).
"""
from __future__ import annotations

import time

import numpy as np
from lidar_quality_core.pointcloud import CloudFormatError
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray

from .cloud_input import read_cloud
from .detector import PROB_NAMES, ReferenceDetector
from .messages import detection_array


def detector_messages(header, out):
    """(detections, proposals) Detection3DArrays of a DetectorOutput."""
    fg = out.class_probs[:, 1:]
    dets = detection_array(header, out.boxes[out.keep], fg[out.keep], PROB_NAMES[1:],
                           ids=out.keep.tolist())
    props = detection_array(header, out.boxes, fg, PROB_NAMES[1:])
    return dets, props


class DetectorNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("detector_node", **kwargs)
        model_dir = declare(self, "model_dir", "",
                            "Directory of the trained detector (detector.json + models); "
                            "empty: the shipped models/reference.", read_only=True)
        self.publish_proposals = declare(self, "publish_proposals", True,
                                         "Also publish the pre-NMS proposals on output/proposals.")
        self.detector = ReferenceDetector(model_dir or None)
        self.pub_det = self.create_publisher(Detection3DArray, "output/detections", output_qos(5))
        self.pub_prop = self.create_publisher(Detection3DArray, "output/proposals", output_qos(5))
        self.inputs = SyncedInputs(self, [(PointCloud2, "input/points")], self.on_frame,
                                   diagnostics=self.diag, **self.declare_sync_parameters())
        self.get_logger().info("detector_node ready")

    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        msg = synced.messages[0]
        try:
            cloud = read_cloud(msg)
        except CloudFormatError as exc:
            self.warn_input("cloud", f"dropping frame: malformed input/points: {exc}")
            self.diag.frame_dropped("malformed_cloud")
            return
        self.diag.clear("cloud")
        ok = cloud.finite
        ring = None if cloud.ring is None else cloud.ring[ok]
        out = self.detector.detect(cloud.xyz[ok], cloud.intensity[ok], ring)
        dets, props = detector_messages(msg.header, out)
        self.pub_det.publish(dets)
        if self.publish_proposals:
            self.pub_prop.publish(props)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(DetectorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
