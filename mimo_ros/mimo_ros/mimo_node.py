"""``mimo_node``: the LiDAR-MIMO node shell.

Subscribes to ``input/head_0`` ... ``input/head_{K-1}`` (Detection3DArray, K =
``num_heads``), matches the heads by stamp and validates their boxes. Clustering,
merging and the meta models are not in this node yet: it publishes no detections until
they are, only /diagnostics.
"""
from __future__ import annotations

import time

from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from vision_msgs.msg import Detection3DArray


class MimoNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("mimo_node", **kwargs)
        self.num_heads = declare(self, "num_heads", 2,
                                 "Number K of detector heads, subscribed as input/head_0 .. "
                                 "input/head_{K-1}.", min_value=1, max_value=16)
        topics = [(Detection3DArray, f"input/head_{k}") for k in range(self.num_heads)]
        self.inputs = SyncedInputs(self, topics, self.on_frame, diagnostics=self.diag,
                                   **self.declare_sync_parameters())
        self.get_logger().info(f"mimo_node ready, inputs: {', '.join(self.inputs.topics)}")

    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        invalid = 0
        for head in synced.messages:
            invalid += int((~detections_to_arrays(head).valid).sum())
        if invalid:
            self.warn_input("detections", f"{invalid} invalid head box(es) in this frame")
        else:
            self.diag.clear("detections")
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(MimoNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
