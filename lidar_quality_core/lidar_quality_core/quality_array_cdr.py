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
from numba import njit, types

from .kernel_types import array_in, array_out

U32 = struct.Struct("<I")


def cdr_string(text: str) -> bytes:
    """A CDR string: uint32 length (the NUL included), UTF-8 bytes, NUL."""
    b = text.encode("utf-8") + b"\0"
    return U32.pack(len(b)) + b


def cdr_strings(texts) -> tuple[np.ndarray, np.ndarray]:
    """The CDR strings of ``texts`` (any objects, as ``str``) one after the other, as
    uint8, and where each starts (``len + 1`` offsets): input of the compiled writers.

    ASCII texts without NUL (ids, class names: the usual case) are encoded at once and
    framed by one compiled pass (100 ids and 99 class names: 59 us by :func:`cdr_string`
    each, 20 us so); others string by string."""
    strs = [t if type(t) is str else str(t) for t in texts]
    joined = "\0".join(strs)
    if not (joined.isascii() and joined.count("\0") == len(strs) - 1):
        entries = [cdr_string(t) for t in strs]
        at = np.zeros(len(entries) + 1, np.int64)
        np.cumsum([len(e) for e in entries], out=at[1:])
        return np.frombuffer(b"".join(entries), np.uint8), at
    lengths = np.fromiter(map(len, strs), np.int64, len(strs))
    return _framed(np.frombuffer(joined.encode("ascii"), np.uint8), lengths)


@njit(types.Tuple((array_out(types.uint8), array_out(types.int64)))(
    array_in(types.uint8), array_in(types.int64)), cache=True, nogil=True)
def _framed(joined, lengths):
    # ``joined``: the texts with one NUL between each two; each text becomes its uint32
    # length (NUL included), its bytes and the NUL
    n = len(lengths)
    at = np.zeros(n + 1, np.int64)
    for i in range(n):
        at[i + 1] = at[i] + 5 + lengths[i]
    out = np.empty(at[n], np.uint8)
    src = 0
    for i in range(n):
        m = lengths[i] + 1
        p = at[i]
        for b in range(4):
            out[p + b] = (m >> (8 * b)) & 0xFF
        out[p + 4:p + 3 + m] = joined[src:src + m - 1]
        out[p + 3 + m] = 0
        src += m
    return out, at


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


@njit(inline="always")
def put_u32(out, at, v):
    """Write ``v`` as a little-endian uint32 at byte ``at`` of the uint8 array ``out``
    (for the compiled entry writers)."""
    for b in range(4):
        out[at + b] = (v >> (8 * b)) & 0xFF


@njit(array_out(types.uint8)(types.int64, array_in(types.uint8), array_in(types.int64),
                             array_in(types.uint8), array_in(types.int64), array_in(types.int64),
                             types.boolean, array_in(types.uint8, 2)), cache=True, nogil=True)
def _entries(start, ids, id_at, classes, class_at, counts, with_counts, values):
    # Two passes over the entries (size, then bytes), positions relative to byte 4 of the
    # message as in ``pad``; ``ids`` / ``classes`` are whole CDR strings (``cdr_strings``),
    # ``values`` row i is entry i's float64s as little-endian bytes.
    n = len(id_at) - 1
    width = values.shape[1]
    p = start
    for i in range(n):
        p += (-(p - 4)) % 4 + 4 + id_at[i + 1] - id_at[i]
        p += (-(p - 4)) % 4 + class_at[i + 1] - class_at[i]
        if with_counts:
            p += (-(p - 4)) % 4 + 4
        p += (-(p - 4)) % 8 + width
    out = np.zeros(p - start, np.uint8)
    p = start
    for i in range(n):
        p += (-(p - 4)) % 4
        put_u32(out, p - start, i)
        k = id_at[i + 1] - id_at[i]
        out[p + 4 - start:p + 4 + k - start] = ids[id_at[i]:id_at[i + 1]]
        p += 4 + k
        p += (-(p - 4)) % 4
        k = class_at[i + 1] - class_at[i]
        out[p - start:p + k - start] = classes[class_at[i]:class_at[i + 1]]
        p += k
        if with_counts:
            p += (-(p - 4)) % 4
            put_u32(out, p - start, counts[i])
            p += 4
        p += (-(p - 4)) % 8
        out[p - start:p + width - start] = values[i]
        p += width
    return out


def append_entries(out: bytearray, detection_ids, class_ids, figures, counts=None) -> None:
    """Entries of a detection's kind to ``out``: entry ``i`` is uint32 ``i``, string
    ``detection_ids[i]``, string ``class_ids[i]``, uint32 ``counts[i]`` (only when
    ``counts`` is given), then row ``i`` of ``figures`` (n, k) as k float64. One compiled
    pass (``_entries``): in Python, ~20 steps an entry cost a MIMO frame 0.3 ms."""
    values = np.ascontiguousarray(np.asarray(figures, dtype="<f8"))
    ids, id_at = cdr_strings(detection_ids)
    classes, class_at = cdr_strings(class_ids)
    if len(class_at) != len(id_at):
        raise ValueError(f"{len(class_at) - 1} class ids for {len(id_at) - 1} detections")
    if values.ndim != 2 or len(values) != len(id_at) - 1:
        raise ValueError(f"figures must be ({len(id_at) - 1}, k), got {values.shape}")
    n_counts = np.zeros(0, np.int64) if counts is None else np.asarray(counts, np.int64).reshape(-1)
    if counts is not None and len(n_counts) != len(id_at) - 1:
        raise ValueError(f"{len(n_counts)} counts for {len(id_at) - 1} detections")
    out += _entries(len(out), ids, id_at, classes, class_at, n_counts, counts is not None,
                    values.view(np.uint8).reshape(len(values), 8 * values.shape[1])).tobytes()


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
