"""lidar_quality_msgs/SegmentQualityArray written as its serialized (CDR) bytes.

Why: lms_node publishes one entry per segment, about 2000 a frame. Building them as
Python messages took 1.1-1.5 ms and rclpy's conversion of the array for publishing
another 2.0 ms (measured, one 64 x 2048 frame, 2051 segments); written here from the
frame's arrays it is a few array operations. The bytes are what rclpy serializes for the
same message (padding bytes aside; ``test_segment_quality_cdr`` compares them).

Layout (plain little-endian CDR, ``00 01``; each primitive aligned to its size relative
to the end of the 4-byte encapsulation header): header (stamp, frame_id), the two model
ids, the segments (uint32 segment_id, uint16 class_index, string class_name, uint32
point_count, uint32 projected_point_count, float64 confidence, float64 predicted_iou),
then the version-1 fields (uint8 version, uint8 drift_level, float32 drift_score, uint32
drift_window_frames, string drift_quantities, bool passthrough). A segment ends on an
8-byte boundary (its last field is a float64), so every segment after the first starts
on one and has a size that depends on its class name only. No rclpy.
"""
from __future__ import annotations

import numpy as np

from .quality_array_cdr import append_version_fields, array_head, cdr_string

__all__ = ["encode_segment_quality_array"]


def encode_segment_quality_array(header, confidence_model_id: str, iou_model_id: str,
                                 class_index, class_names, point_count,
                                 projected_point_count, confidence, predicted_iou, *,
                                 version: int, drift_level: int, drift_score: float,
                                 drift_window_frames: int, drift_quantities: str,
                                 passthrough: bool) -> bytes:
    """Serialized SegmentQualityArray: segment ``i`` has ``segment_id = i``, class
    ``class_index[i]`` (named ``class_names[class_index[i]]``), the counts, confidence
    and predicted IoU at ``i`` (arrays of one length); the keyword fields as in
    ``DomainVerdict.message_fields``."""
    cls = np.asarray(class_index, dtype=np.int64).reshape(-1)
    n = len(cls)
    head = array_head(header, confidence_model_id, iou_model_id, n)
    first = len(head)
    # per class: the name as CDR string words, and where point_count sits in the entry
    names = [cdr_string(c) for c in class_names]
    name_words = [np.frombuffer(s + b"\0" * (-len(s) % 4), "<u4") for s in names]
    counts_at = np.array([8 + 4 * len(w) for w in name_words], dtype=np.int64)
    # offsets from the entry's start; the float64 pair 8-aligned (relative to byte 4)
    at = counts_at[cls] + 8
    phase = np.zeros(n, dtype=np.int64)
    if n:
        phase[0] = (first - 4) % 8
    doubles_at = at + (-(at + phase) % 8)
    size = doubles_at + 16
    starts = first + np.concatenate([[0], np.cumsum(size[:-1])]) if n else np.zeros(0, np.int64)
    end = first + int(size.sum())
    words = np.zeros((end + 3) // 4, dtype="<u4")
    w0 = starts // 4
    words[w0] = np.arange(n)
    words[w0 + 1] = cls  # uint16 class_index, then two padding bytes
    for c in np.unique(cls).tolist():  # one pass per class present (a few)
        rows = w0[cls == c] + 2
        words[rows[:, None] + np.arange(len(name_words[c]))] = name_words[c]
    pc = w0 + counts_at[cls] // 4
    words[pc] = np.asarray(point_count, dtype=np.int64)
    words[pc + 1] = np.asarray(projected_point_count, dtype=np.int64)
    dw = (starts + doubles_at) // 4
    pair = np.column_stack([np.asarray(confidence, dtype="<f8"),
                            np.asarray(predicted_iou, dtype="<f8")]).view("<u4")
    words[dw[:, None] + np.arange(4)] = pair.reshape(n, 4)
    out = bytearray(words.tobytes()[:end])
    out[:first] = head
    return append_version_fields(
        out, version=version, drift_level=drift_level, drift_score=drift_score,
        drift_window_frames=drift_window_frames, drift_quantities=drift_quantities,
        passthrough=passthrough)
