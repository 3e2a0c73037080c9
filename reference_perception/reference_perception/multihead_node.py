"""``multihead_node``: the reference multi-head (MIMO-style) detector as a ROS 2 node.

Subscribes to ``input/points`` and publishes per head k (``num_heads``, at most the number
of trained heads) ``output/head_k`` (Detection3DArray: the head's post-NMS boxes, class
distribution as hypotheses, x / y / z / yaw variances on the pose covariance diagonal) and
``output/head_k/variance`` (BoxVarianceArray: all seven box variances), with the cloud's
header. Detection ids are indices of the shared candidate set, so boxes of different heads
with the same id come from the same candidate.
"""
from __future__ import annotations

import time

from lidar_quality_core.pointcloud import CloudFormatError
from lidar_quality_msgs.msg import BoxVarianceArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray

from .cloud_input import read_cloud
from .detector import PROB_NAMES
from .messages import box_variance_array, detection_array
from .multihead import MultiHeadDetector


def head_messages(header, out):
    """[(Detection3DArray, BoxVarianceArray)] per head of a MultiHeadOutput."""
    msgs = []
    for h in out.heads:
        ids = h.keep.tolist()
        msgs.append((detection_array(header, h.boxes[h.keep], h.class_probs[h.keep, 1:],
                                     PROB_NAMES[1:], ids=ids, variances=h.variances[h.keep]),
                     box_variance_array(header, h.variances[h.keep], ids=ids)))
    return msgs


class MultiHeadNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("multihead_node", **kwargs)
        model_dir = declare(self, "model_dir", "",
                            "Directory of the trained heads (multihead.json + models); empty: "
                            "the shipped models/reference.", read_only=True)
        k = declare(self, "num_heads", 2, "Number of heads to run and publish (1..trained).",
                    read_only=True, min_value=1, max_value=4)
        self.detector = MultiHeadDetector(model_dir or None, num_heads=k)
        self.pubs = [(self.create_publisher(Detection3DArray, f"output/head_{i}", output_qos(5)),
                      self.create_publisher(BoxVarianceArray, f"output/head_{i}/variance", output_qos(5)))
                     for i in range(k)]
        self.inputs = SyncedInputs(self, [(PointCloud2, "input/points")], self.on_frame,
                                   diagnostics=self.diag, **self.declare_sync_parameters())
        self.get_logger().info(f"multihead_node ready, {k} heads")

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
        for (p_det, p_var), (dets, var) in zip(self.pubs, head_messages(msg.header, out)):
            p_det.publish(dets)
            p_var.publish(var)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(MultiHeadNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
