"""``detector_node``: the reference 3D detector as a ROS 2 node.

Subscribes to ``input/points`` (PointCloud2) and publishes ``output/detections`` (post-NMS
Detection3DArray) and ``output/proposals`` (pre-NMS Detection3DArray), both with the
cloud's header. Each detection carries the class distribution as hypotheses and the id of
the proposal it came from (see :mod:`reference_perception.messages`).
"""
from __future__ import annotations

from lidar_quality_core.frame import FrameOutputs
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from vision_msgs.msg import Detection3DArray

from .cloud_node import CloudNode
from .detector import PROB_NAMES, ReferenceDetector
from .messages import detector_messages


class DetectorNode(CloudNode):
    def __init__(self, **kwargs):
        super().__init__("detector_node", **kwargs)
        model_dir = declare(self, "model_dir", "",
                            "Directory of the trained detector (detector.json + models); "
                            "empty: the shipped models/reference.", read_only=True)
        self.publish_proposals = declare(self, "publish_proposals", True,
                                         "Also publish the pre-NMS proposals on output/proposals.")
        self.detector = ReferenceDetector(model_dir or None)
        self.create_output(Detection3DArray, "output/detections", output_qos(5))
        self.create_output(Detection3DArray, "output/proposals", output_qos(5))
        self.subscribe_points()
        self.get_logger().info("detector_node ready")

    def process_cloud(self, header, cloud) -> FrameOutputs:
        out = self.detector.detect(*cloud.finite_points())
        dets, props = detector_messages(header, out, PROB_NAMES[1:])
        msgs = {"output/detections": dets}
        if self.publish_proposals:
            msgs["output/proposals"] = props
        return FrameOutputs(msgs)


def main(args=None) -> int:
    return run_node(DetectorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
