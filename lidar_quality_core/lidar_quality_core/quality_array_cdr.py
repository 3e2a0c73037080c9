"""The framing the suite's quality arrays share on the wire, written as CDR bytes:
``segment_quality_cdr`` (SegmentQualityArray), ``detection_quality_cdr``
(DetectionQualityArray) and ``cluster_uncertainty_cdr`` (ClusterUncertaintyArray) write
their entries between these; the last two entries of one shape (:func:`append_entries`).

Plain little-endian CDR (``00 01``); each primitive is aligned to its size relative to
the end of the 4-byte encapsulation header. Head: header (stamp, frame_id), the two model
ids, the entry count. Tail (message version 1): uint8 version, uint8 drift_level, float32
drift_score, uint32 drift_window_frames, string drift_quantities, bool passthrough.
No rclpy.
"""
from __future__ import annotations

import struct

import numpy as np

U32 = struct.Struct("<I")


def cdr_string(text: str) -> bytes:
    """A CDR string: uint32 length (the NUL included), UTF-8 bytes, NUL."""
    b = text.encode("utf-8") + b"\0"
    return U32.pack(len(b)) + b


def pad(buf: bytearray, align: int) -> None:
    """Zero bytes up to the next multiple of ``align`` (relative to byte 4)."""
    buf += b"\0" * (-(len(buf) - 4) % align)


def array_head(header, confidence_model_id: str, iou_model_id: str, n: int) -> bytearray:
    """Encapsulation, header, model ids and the count ``n`` of the entries that follow."""
    head = bytearray(b"\x00\x01\x00\x00")
    head += struct.pack("<iI", header.stamp.sec, header.stamp.nanosec)
    head += cdr_string(header.frame_id)
    for text in (confidence_model_id, iou_model_id):
        pad(head, 4)
        head += cdr_string(text)
    pad(head, 4)
    head += U32.pack(n)
    return head


def append_entries(out: bytearray, detection_ids, class_ids, figures, counts=None) -> None:
    """Entries of a detection's kind to ``out``: entry ``i`` is uint32 ``i``, string
    ``detection_ids[i]``, string ``class_ids[i]``, uint32 ``counts[i]`` (only when
    ``counts`` is given), then row ``i`` of ``figures`` (n, k) as k float64."""
    values = np.asarray(figures, dtype="<f8")
    width = 8 * values.shape[1]
    values = values.tobytes()
    counts = None if counts is None else np.asarray(counts, dtype=np.int64).reshape(-1).tolist()
    for i, (did, cid) in enumerate(zip(detection_ids, class_ids)):
        pad(out, 4)
        out += U32.pack(i)
        out += cdr_string(str(did))
        pad(out, 4)
        out += cdr_string(str(cid))
        if counts is not None:
            pad(out, 4)
            out += U32.pack(counts[i])
        pad(out, 8)
        out += values[width * i:width * (i + 1)]


def append_version_fields(out: bytearray, *, version: int, drift_level: int,
                          drift_score: float, drift_window_frames: int,
                          drift_quantities: str, passthrough: bool) -> bytes:
    """``out`` with the version-1 fields (``DomainVerdict.message_fields``) appended."""
    out += struct.pack("<BB", version, drift_level)
    pad(out, 4)
    out += struct.pack("<fI", drift_score, drift_window_frames)
    out += cdr_string(drift_quantities)
    out += struct.pack("<?", passthrough)
    return bytes(out)
