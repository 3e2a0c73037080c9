"""``segmenter_node``: the reference point-cloud segmenter as a ROS 2 node.

Subscribes to ``input/points`` (PointCloud2 with x, y, z, intensity, optional ring) and
publishes ``output/points``: the same points in the same order with one probability field
per class (see :mod:`reference_perception.messages`; class names in the order of the
``class_names`` parameter, read-only), float32 or uint8-quantised.
"""
from __future__ import annotations

import numpy as np
from lidar_quality_core.frame import FrameOutputs
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_sim.classes import CLASS_NAMES
from sensor_msgs.msg import PointCloud2

from .cloud_node import CloudNode
from .messages import QUANTIZE_DEFAULT, probability_cloud
from .segmenter import DEFAULT_MODEL_PATH, ReferenceSegmenter


class SegmenterNode(CloudNode):
    def __init__(self, **kwargs):
        super().__init__("segmenter_node", **kwargs)
        path = declare(self, "model_path", "",
                       "Segmenter model file (model store); empty: the shipped "
                       "models/reference segmenter.", read_only=True)
        self.quantize = declare(self, "quantize_probabilities", QUANTIZE_DEFAULT,
                                "Publish probabilities as uint8 (round(p * 255): a quarter of "
                                "the bytes) instead of float32.")
        declare(self, "class_names", list(CLASS_NAMES),
                "Class of each probability field, in field order (fixed by the model).",
                read_only=True)
        self.segmenter = ReferenceSegmenter.load(path or DEFAULT_MODEL_PATH)
        self.create_output(PointCloud2, "output/points", output_qos(5))
        self.subscribe_points()
        self.get_logger().info(f"segmenter_node ready, model {self.segmenter.model_id}")

    def process_cloud(self, header, cloud) -> FrameOutputs:
        if not cloud.has_intensity:
            self.warn_input("intensity", "input/points has no intensity field: using 0")
        # non-finite points keep their place and get the uniform distribution
        probs = self.segmenter.predict_proba(cloud.xyz, cloud.intensity, cloud.ring)
        xyz = np.where(cloud.finite[:, None], cloud.xyz, np.nan).astype(np.float32)
        return FrameOutputs({"output/points": probability_cloud(
            header, xyz, cloud.intensity, probs, CLASS_NAMES, quantize=self.quantize)})


def main(args=None) -> int:
    return run_node(SegmenterNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
