"""Box-geometry benchmarks on one synthetic frame (120k points, 50 detections, 500 proposals).

Figures: ``core.points_in_boxes_120k_550_ms`` (targets <= 5 ms), ``core.iou_bev_50x500_ms``
(<= 2 ms), ``core.iou_3d_50x500_ms`` (<= 3 ms), ``core.nms_500_ms``.
"""
from __future__ import annotations

import numpy as np

from lidar_quality_core.box_geometry import points_in_boxes
from lidar_quality_core.iou import iou_3d, iou_bev
from lidar_quality_core.nms import rotated_nms
from lidar_quality_core.synthetic import synthetic_frame


def figures():
    f = synthetic_frame(n_points=120_000, n_objects=50, n_proposals=500, seed=0)
    boxes = np.concatenate([f.detections, f.proposals])

    yield "core.points_in_boxes_120k_550_ms", lambda: points_in_boxes(f.points, boxes)
    yield "core.iou_bev_50x500_ms", lambda: iou_bev(f.detections, f.proposals)
    yield "core.iou_3d_50x500_ms", lambda: iou_3d(f.detections, f.proposals)
    yield "core.nms_500_ms", lambda: rotated_nms(f.proposals, f.prop_scores, 0.5)
