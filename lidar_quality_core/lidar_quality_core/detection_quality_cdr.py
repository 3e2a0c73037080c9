"""lidar_quality_msgs/DetectionQualityArray written as its serialized (CDR) bytes.

Why: lmd_node publishes one entry per scored detection, every frame. Building ~50 Python
messages and having rclpy convert them for publishing cost a few tenths of a millisecond
of every LMD frame; written here from the frame's arrays it is one loop over the
detections (``quality_array_cdr.append_entries``, shared with MIMO's uncertainty array).
The bytes are what rclpy serializes for the same message (padding bytes aside;
``test_detection_quality_cdr`` compares them).

Layout (plain little-endian CDR, framing of ``quality_array_cdr``): header, the two model
ids, the detections (uint32 detection_index, string detection_id, string class_id, then
three float64: original_score, confidence, predicted_iou), then the version-1 fields.
No rclpy.
"""
from __future__ import annotations

import numpy as np

from .quality_array_cdr import append_entries, append_version_fields, array_head

__all__ = ["encode_detection_quality_array"]


def encode_detection_quality_array(header, confidence_model_id: str, iou_model_id: str,
                                   detection_ids, class_ids, figures, *, version: int,
                                   drift_level: int, drift_score: float,
                                   drift_window_frames: int, drift_quantities: str,
                                   passthrough: bool) -> bytes:
    """Serialized DetectionQualityArray: entry ``i`` has ``detection_index = i``,
    ``detection_ids[i]``, ``class_ids[i]`` and row ``i`` of ``figures`` (n, 3):
    original score, confidence, predicted IoU; the keyword fields as in
    ``DomainVerdict.message_fields``."""
    n = len(detection_ids)
    out = array_head(header, confidence_model_id, iou_model_id, n)
    append_entries(out, detection_ids, class_ids, np.asarray(figures).reshape(n, 3))
    return append_version_fields(
        out, version=version, drift_level=drift_level, drift_score=drift_score,
        drift_window_frames=drift_window_frames, drift_quantities=drift_quantities,
        passthrough=passthrough)
