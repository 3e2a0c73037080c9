"""lidar_quality_msgs/SegmentQualityArray written as its serialized (CDR) bytes.

Why: lms_node publishes one entry per segment, about 2000 a frame. Building them as
Python messages took 1.1-1.5 ms and rclpy's conversion of the array for publishing
another 2.0 ms (measured, one 64 x 2048 frame, 2051 segments); written here from the
frame's arrays by one compiled writer the whole message costs 0.18 ms. The bytes are what
rclpy serializes for the same message (padding bytes aside; ``test_segment_quality_cdr``
compares them).

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
from numba import njit, types

from .kernel_types import array_in, array_out
from .quality_array_cdr import append_version_fields, array_head, cdr_strings, put_u32

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
    cls = np.ascontiguousarray(class_index, dtype=np.int64).reshape(-1)
    n = len(cls)
    if n and (cls.min() < 0 or cls.max() >= len(class_names)):
        raise ValueError(f"class_index outside 0..{len(class_names) - 1}")
    counts = np.column_stack([np.asarray(point_count, np.int64).reshape(-1),
                              np.asarray(projected_point_count, np.int64).reshape(-1)])
    values = np.column_stack([np.asarray(confidence, "<f8").reshape(-1),
                              np.asarray(predicted_iou, "<f8").reshape(-1)])
    if len(counts) != n or len(values) != n:
        raise ValueError(f"counts, confidence and predicted_iou must have {n} entries")
    head = array_head(header, confidence_model_id, iou_model_id, n)
    names, name_at = cdr_strings(class_names)
    out = head + _segments(len(head), cls, names, name_at, np.ascontiguousarray(counts),
                           values.view(np.uint8).reshape(n, 16)).tobytes()
    return append_version_fields(
        out, version=version, drift_level=drift_level, drift_score=drift_score,
        drift_window_frames=drift_window_frames, drift_quantities=drift_quantities,
        passthrough=passthrough)


@njit(array_out(types.uint8)(types.int64, array_in(types.int64), array_in(types.uint8),
                             array_in(types.int64), array_in(types.int64, 2),
                             array_in(types.uint8, 2)), cache=True, nogil=True)
def _segments(start, cls, names, name_at, counts, values):
    # The entries from byte ``start`` of the message, positions relative to its byte 4 as
    # in ``quality_array_cdr.pad``; padding bytes zero. ``names``: the class names as
    # whole CDR strings (``cdr_strings``); ``values`` row i: entry i's two float64 as
    # little-endian bytes. Two passes (size, then bytes): as numpy array operations, with
    # a pass per class present, the message of 2049 segments took 0.37 ms, with this
    # writer (0.05 of it) 0.18.
    n = len(cls)
    p = start
    for i in range(n):
        # id, class index (+2 padding), the name (4-aligned after the uint16 pair), the
        # two counts (4-aligned), the two float64 (8-aligned)
        p += 8 + name_at[cls[i] + 1] - name_at[cls[i]]
        p += (-(p - 4)) % 4 + 8
        p += (-(p - 4)) % 8 + 16
    out = np.zeros(p - start, np.uint8)
    p = start
    for i in range(n):
        c = cls[i]
        put_u32(out, p - start, i)
        out[p + 4 - start] = c & 0xFF
        out[p + 5 - start] = (c >> 8) & 0xFF
        q, k = p + 8 - start, name_at[c + 1] - name_at[c]
        for b in range(k):  # element loops: a slice is a view object an entry
            out[q + b] = names[name_at[c] + b]
        p += 8 + k
        p += (-(p - 4)) % 4
        put_u32(out, p - start, counts[i, 0])
        put_u32(out, p + 4 - start, counts[i, 1])
        p += 8
        p += (-(p - 4)) % 8
        for b in range(16):
            out[p - start + b] = values[i, b]
        p += 16
    return out
