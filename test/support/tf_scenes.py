"""Scenes published in another frame: a Detection3DArray's boxes moved by a transform."""
from __future__ import annotations

import copy

from lidar_quality_core.boxes import detections_to_arrays, yaw_to_quaternion


def detections_in_frame(msg, t, frame_id: str):
    """A copy of Detection3DArray ``msg`` with its (upright) boxes moved by ``t``
    (``lidar_quality_core.transforms.Transform``) and its header's frame_id ``frame_id``
    (same stamp)."""
    out = copy.deepcopy(msg)
    out.header.frame_id = frame_id
    moved, _ = t.apply_boxes(detections_to_arrays(msg).boxes)
    for d, b, q in zip(out.detections, moved, yaw_to_quaternion(moved[:, 6])):
        p, o = d.bbox.center.position, d.bbox.center.orientation
        p.x, p.y, p.z = b[:3].tolist()
        o.x, o.y, o.z, o.w = q.tolist()
    return out
