"""``multihead_node``: the reference multi-head (MIMO-style) detector as a ROS 2 node.

Subscribes to ``input/points`` and publishes per head k (``num_heads``, at most the number
of trained heads) ``output/head_k`` (Detection3DArray: the head's post-NMS boxes, class
distribution as hypotheses, x / y / z / yaw variances on the pose covariance diagonal) and
``output/head_k/variance`` (BoxVarianceArray: all seven box variances), with the cloud's
header. Detection ids are indices of the shared candidate set, so boxes of different heads
with the same id come from the same candidate.
"""
from __future__ import annotations

from lidar_quality_core.frame import FrameOutputs
from lidar_quality_msgs.msg import BoxVarianceArray
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from vision_msgs.msg import Detection3DArray

from .cloud_node import CloudNode
from .detector import PROB_NAMES
from .messages import head_messages
from .multihead import MultiHeadDetector


class MultiHeadNode(CloudNode):
    def __init__(self, **kwargs):
        super().__init__("multihead_node", **kwargs)
        model_dir = declare(self, "model_dir", "",
                            "Directory of the trained heads (multihead.json + models); empty: "
                            "the shipped models/reference.", read_only=True)
        k = declare(self, "num_heads", 2, "Number of heads to run and publish (1..trained).",
                    read_only=True, min_value=1, max_value=4)
        self.detector = MultiHeadDetector(model_dir or None, num_heads=k)
        for i in range(k):
            self.create_output(Detection3DArray, f"output/head_{i}", output_qos(5))
            self.create_output(BoxVarianceArray, f"output/head_{i}/variance", output_qos(5))
        self.subscribe_points()
        self.get_logger().info(f"multihead_node ready, {k} heads")

    def process_cloud(self, header, cloud) -> FrameOutputs:
        out = self.detector.detect(*cloud.finite_points())
        msgs = {}
        for i, (dets, var) in enumerate(head_messages(header, out, PROB_NAMES[1:])):
            msgs[f"output/head_{i}"] = dets
            msgs[f"output/head_{i}/variance"] = var
        return FrameOutputs(msgs)


def main(args=None) -> int:
    return run_node(MultiHeadNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
