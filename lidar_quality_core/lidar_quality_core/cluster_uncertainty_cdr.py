"""lidar_quality_msgs/ClusterUncertaintyArray written as its serialized (CDR) bytes.

Why: mimo_node publishes one entry per merged detection, every frame. Building the
entries as Python messages and having rclpy convert them for publishing cost about a
tenth of a MIMO frame; written here from the frame's arrays it is one loop over the
clusters (a few dozen) with the seven float64 figures of all of them packed at once. The
bytes are what rclpy serializes for the same message (padding bytes aside;
``test_cluster_uncertainty_cdr`` compares them).

Layout (plain little-endian CDR, ``00 01``; each primitive aligned to its size relative
to the end of the 4-byte encapsulation header): header (stamp, frame_id), the two model
ids, the clusters (uint32 detection_index, string detection_id, string class_id, uint32
cluster_size, then seven float64: shannon_entropy, aleatoric_entropy,
mutual_information, epistemic_total_variance, aleatoric_total_variance, confidence,
predicted_iou), then the version-1 fields (uint8 version, uint8 drift_level, float32
drift_score, uint32 drift_window_frames, string drift_quantities, bool passthrough).
No rclpy.
"""
from __future__ import annotations

import numpy as np

from .quality_array_cdr import append_entries, append_version_fields, array_head

__all__ = ["encode_cluster_uncertainty_array"]


def encode_cluster_uncertainty_array(header, confidence_model_id: str, iou_model_id: str,
                                     detection_ids, class_ids, cluster_size, figures, *,
                                     version: int, drift_level: int, drift_score: float,
                                     drift_window_frames: int, drift_quantities: str,
                                     passthrough: bool) -> bytes:
    """Serialized ClusterUncertaintyArray: cluster ``i`` has ``detection_index = i``,
    ``detection_ids[i]``, ``class_ids[i]``, ``cluster_size[i]`` and row ``i`` of
    ``figures`` (C, 7): Shannon entropy, aleatoric entropy, mutual information, ETV, ATV,
    confidence, predicted IoU; the keyword fields as in ``DomainVerdict.message_fields``."""
    n = len(detection_ids)
    out = array_head(header, confidence_model_id, iou_model_id, n)
    append_entries(out, detection_ids, class_ids, np.asarray(figures).reshape(n, 7),
                   counts=cluster_size)
    return append_version_fields(
        out, version=version, drift_level=drift_level, drift_score=drift_score,
        drift_window_frames=drift_window_frames, drift_quantities=drift_quantities,
        passthrough=passthrough)
