"""vision_msgs/Detection3DArray read from and written to its serialized (CDR) bytes.

Why: rclpy turns a received Detection3DArray into one Python object per nested message,
and each generated ``__init__`` first builds defaults of all its sub-messages. A
reference-detector proposal array (~450 boxes x 4 hypotheses, 0.8 MB) takes 100-300 ms to
deserialize that way, which is 10-20x the whole LMD frame. A node that subscribes with
``raw=True`` (``SyncedInputs(..., raw_decoders=...)``) and decodes here gets the
:class:`~lidar_quality_core.boxes.DetectionArrays` in ~0.4 ms, and can publish its re-scored
output as bytes (``rclpy`` publishers take serialized messages).

The variable-length layout is walked by one compiled function (numba, cached), which
also groups the class names; a second reads the fixed-size fields (``_fields``). For the
usual message both, the ids and ``boxes``' compiled hypothesis rules run in one compiled
call (``_decode``: a 100-box array 297 -> 217 us with cold caches, 114 -> 84 warm). Bytes
the walk cannot follow go to the same walk in Python (``_layout_loop``), which says where
and why they end. With the compiled hypothesis rules of ``boxes.arrays_from_fields``: 500
proposals 0.27 ms back to back, 0.57 ms once per frame after idling (with the Python
walk and numpy rules: 0.95 / 1.7 ms); 50 detections 0.07 / 0.47 ms (0.30 / 0.93). The
writers (``encode_detection_array``, ``encode_detections``) are compiled passes too.

Format: the 4-byte encapsulation header (plain little-endian CDR, ``00 01``, as ROS 2's
DDS layers write ROS messages on little-endian machines), then the fields in order, each
primitive aligned to its size relative to the end of the encapsulation header; strings
are a uint32 length (including the NUL) and the bytes; sequences a uint32 count.
Detection3D: header (stamp sec int32, nanosec uint32, frame_id), results[]
(class_id, score float64, pose: 7 float64, covariance: 36 float64), bbox (centre: 7
float64, size: 3 float64), id. Anything else (other encapsulations, truncated data)
raises :class:`CdrError`. No rclpy; ``std_msgs`` only for the decoded header.
"""
from __future__ import annotations

import struct
import sys
from dataclasses import dataclass

import numpy as np
from numba import njit, types

from .boxes import (DetectionArrays, arrays_from_fields, arrays_from_table, decoded_header,
                    hypothesis_table, rpy_angles, rpy_terms, yaw_to_quaternion)
from .kernel_types import array_in, array_out
from .quality_array_cdr import cdr_strings

__all__ = ["CdrError", "read_string", "DecodedDetections", "decode_detection_array",
           "encode_detection_array", "rescaled_scores", "encode_detections"]

_ENCAPS = {b"\x00\x01": "<"}
_N_HYP_DOUBLES = 44  # score + pose (7) + covariance (36), contiguous and 8-aligned
_PAD = [b"\0" * k for k in range(8)]


class CdrError(ValueError):
    """Serialized bytes that are not a Detection3DArray this module can read."""


class _Fmt:
    def __init__(self, e: str):
        self.u32 = struct.Struct(e + "I")
        self.stamp = struct.Struct(e + "iI")


_FMTS = {e: _Fmt(e) for e in _ENCAPS.values()}


@dataclass
class DecodedDetections:
    """A decoded Detection3DArray: ``header`` (std_msgs/Header), ``arrays`` as from
    ``boxes.detections_to_arrays``, and where each part sits in ``data`` (for
    :func:`encode_detection_array`). Hypotheses are flat, grouped by detection:
    detection ``i`` owns ``hyp_offsets[i]:hyp_offsets[i + 1]``."""

    header: object
    arrays: DetectionArrays
    data: bytes
    endian: str
    det_spans: np.ndarray    # (n, 2) start of the detection, start of its results count
    bbox_at: np.ndarray      # (n,) offset of the 10 bbox doubles
    id_at: np.ndarray        # (n,) offset of the id string
    hyp_offsets: np.ndarray  # (n + 1,) CSR
    hyp_det: np.ndarray      # (H,) owning detection
    hyp_class_at: np.ndarray  # (H,) offset of the class_id string
    hyp_score_at: np.ndarray  # (H,) offset of the score (then pose and covariance)
    hyp_score: np.ndarray    # (H,) float64

    def __len__(self) -> int:
        return len(self.bbox_at)


def read_string(buf, p: int, u32, end: int):
    """(str, offset after it) of the CDR string at ``p`` (already aligned); ``CdrError``
    when it does not fit in ``end`` bytes or is not UTF-8."""
    if p + 4 > end:
        raise CdrError(f"truncated message ({end} bytes): a string at byte {p}")
    (length,) = u32.unpack_from(buf, p)
    q = p + 4 + length
    if length == 0 or q > end:
        raise CdrError(f"bad string at byte {p}: length {length}")
    try:
        return str(buf[p + 4:q - 1], "utf-8"), q  # bytes or a memoryview
    except UnicodeDecodeError as exc:
        raise CdrError(f"string at byte {p} is not UTF-8: {exc}") from None


def open_array(data, what: str, elements: str, min_size: int, *, words: bool = True):
    """``(buf, words, header, n, p)`` of serialized bytes of a ROS message made of a header
    and one sequence (``what``: its type, for errors): the bytes, a uint32 view of them
    indexed by offset / 4 (None unless ``words``), the std_msgs/Header, the sequence
    length and the offset of its first element. ``CdrError`` for another encapsulation,
    truncated bytes, or more ``elements`` than fit at ``min_size`` bytes each."""
    buf = bytes(data)
    # the usual message: its opening read by one compiled call (a node's caches are cold
    # when a message comes: the ~10 Python steps below cost ~40 us there)
    sec, nsec, flen, n, p, ok = _opening(np.frombuffer(buf, np.uint8))
    if ok and n <= (len(buf) - p) // min_size:
        try:
            frame_id = str(buf[16:15 + flen], "utf-8")
        except UnicodeDecodeError:
            pass  # said below
        else:
            return (buf, _words(buf) if words else None, decoded_header(sec, nsec, frame_id),
                    n, p)
    end = len(buf)
    if _ENCAPS.get(buf[:2]) is None or end < 4:
        raise CdrError(f"unsupported encapsulation {buf[:4].hex() or '(empty)'} "
                       "(plain little-endian CDR expected: 0001)")
    w = _words(buf)
    f = _FMTS["<"]
    try:
        sec, nsec = f.stamp.unpack_from(buf, 4)
        frame_id, p = read_string(buf, 12, f.u32, end)
        p += -p % 4
        n = w[p >> 2]
    except (struct.error, IndexError) as exc:
        raise CdrError(f"truncated {what} ({end} bytes): {exc}") from None
    p += 4
    if n > (end - p) // min_size:
        raise CdrError(f"{n} {elements} cannot fit in {end} bytes")
    return buf, w if words else None, decoded_header(sec, nsec, frame_id), n, p


def _words(buf: bytes):
    """A uint32 view of ``buf`` indexed by offset / 4: every uint32 of these layouts sits
    at a multiple of 4 (aligned relative to byte 4), and this view is cheaper than struct
    in the hot loops (a 462-box proposal array decodes in 1.18 instead of 1.32 ms)."""
    end = len(buf)
    return (memoryview(buf)[:end - end % 4].cast("I") if sys.byteorder == "little"
            else np.frombuffer(buf, "<u4", count=end // 4).tolist())


def array_opening(buf: bytes, n: int) -> bytearray:
    """The start of a serialized message like ``buf`` (see :func:`open_array`): its
    encapsulation and header as they are, then a sequence length ``n``."""
    (flen,) = _FMTS["<"].u32.unpack_from(buf, 12)
    out = bytearray(buf[:16 + flen])
    out += _PAD[-(len(out) - 4) % 4]
    out += _FMTS["<"].u32.pack(n)
    return out


def _gather(raw_bytes: np.ndarray, at: np.ndarray, nbytes: int) -> np.ndarray:
    """(len(at), nbytes) uint8: the bytes at each offset ``at``."""
    return raw_bytes[at[:, None] + np.arange(nbytes)]


def _class_codes(buf: bytes, raw_bytes: np.ndarray, at: np.ndarray, lengths: np.ndarray):
    """(codes, names in order of first appearance) of the strings at ``at``: grouped
    by their bytes with one lexsort (a few distinct class names, thousands of entries)."""
    if not len(at):
        return np.zeros(0, dtype=np.int64), []
    width = -(-int(lengths.max()) // 8) * 8
    if int(at.max()) + 4 + width > len(raw_bytes):
        # a short string near the end read as wide as the longest one would run past
        # the buffer (found by fuzzing: a 4096-byte class_id); the excess is masked below
        raw_bytes = np.concatenate([raw_bytes, np.zeros(width, dtype=np.uint8)])
    chars = _gather(raw_bytes, at + 4, width)
    chars[np.arange(width)[None, :] >= lengths[:, None] - 1] = 0  # NUL and beyond
    words = chars.view(np.uint64)  # (n, width / 8): equal rows <=> equal strings
    order = np.lexsort([words[:, j] for j in range(words.shape[1])] + [lengths])  # stable
    srt = np.column_stack([lengths[order], words[order]])
    new = np.ones(len(order), dtype=bool)
    new[1:] = (srt[1:] != srt[:-1]).any(axis=1)
    group = np.cumsum(new) - 1
    starts = np.flatnonzero(new)
    first = order[starts]  # first appearance of each group (the sort is stable)
    rank = np.empty(len(starts), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(starts))
    codes = np.empty(len(at), dtype=np.int64)
    codes[order] = rank[group]
    names = [""] * len(starts)
    for g, i in enumerate(first.tolist()):
        names[rank[g]] = read_string(buf, int(at[i]), _FMTS["<"].u32, len(buf))[0]
    return codes, names


def _layout_loop(buf: bytes, words, p: int, n: int):
    """Where each part of the ``n`` detections from offset ``p`` sits: (spans, bbox_at,
    id_at, ids as bytes, hyp_off, cls_at), walking the layout in Python: the reference of
    ``_walk``, and what reports bytes that end before their layout does."""
    end = len(buf)
    try:
        spans, bbox_at, id_at, ids = [], [], [], []
        hyp_off, cls_at = [0], []
        add_cls = cls_at.append
        # One pass over the variable-length layout, offsets only (the hot loop: one
        # iteration per hypothesis); strings, scores and boxes are gathered afterwards.
        # Offsets stay multiples of 4 from each count to the next string: only the
        # strings' ends and the 8-byte fields need aligning.
        for _ in range(n):
            p += -p % 4
            start = p
            p += 12 + words[(p + 8) >> 2]  # per-detection header: stamp, frame_id
            p += -p % 4
            k = words[p >> 2]
            spans.append((start, p))
            p += 4
            for _ in range(k):
                add_cls(p)
                q = p + 4 + words[p >> 2]
                p = q + (-(q - 4) % 8) + 8 * _N_HYP_DOUBLES
            hyp_off.append(len(cls_at))
            p += -(p - 4) % 8
            bbox_at.append(p)
            p += 80
            p += -p % 4
            id_at.append(p)
            q = p + 4 + words[p >> 2]
            ids.append(buf[p + 4:q - 1])
            p = q
    except (struct.error, IndexError) as exc:
        raise CdrError(f"truncated Detection3DArray ({end} bytes): {exc}") from None
    if p > end:
        raise CdrError(f"truncated Detection3DArray: {end} bytes, need {p}")
    return (np.asarray(spans, dtype=np.int64).reshape(n, 2), bbox_at, id_at, ids,
            hyp_off, cls_at)


_U8 = array_in(types.uint8)
#: more distinct class_id strings than this in one array: grouped by ``_class_codes``
_MAX_CLASSES = 64


@njit(inline="always")
def _u32(raw, at):
    return (np.int64(raw[at]) | (np.int64(raw[at + 1]) << 8) | (np.int64(raw[at + 2]) << 16)
            | (np.int64(raw[at + 3]) << 24))


@njit(types.UniTuple(types.int64, 6)(_U8), cache=True, nogil=True)
def _opening(raw):
    """``(sec, nanosec, frame_id length with its NUL, n, p, ok)`` of :func:`open_array`'s
    message: plain little-endian CDR, the header, the sequence length ``n`` and the offset
    ``p`` of its first element; ``ok`` 0 when the bytes do not hold them (the Python path
    then says why)."""
    end = raw.shape[0]
    if end < 16 or raw[0] != 0 or raw[1] != 1:
        return 0, 0, 0, 0, 0, 0
    sec = _u32(raw, 4)
    if sec >= 2 ** 31:  # int32
        sec -= 2 ** 32
    flen = _u32(raw, 12)
    q = 16 + flen
    p = q + (-q) % 4
    if flen == 0 or p + 4 > end:
        return 0, 0, 0, 0, 0, 0
    return sec, _u32(raw, 8), flen, _u32(raw, p), p + 4, 1


@njit((_U8, types.int64, types.int64), cache=True, nogil=True)
def _walk(raw, p, n):
    """``_layout_loop``'s walk, compiled, plus the class_id grouping of ``_class_codes``
    (codes in order of first appearance, compared byte by byte). Returns ``(ok, spans,
    bbox_at, id_at, id_len, hyp_off, cls_at, cls_len, codes, first_at)``; ``ok`` 0: the
    bytes end before the layout does (the loop then says where), 2: too many distinct
    class names (``_class_codes`` groups them)."""
    end = raw.shape[0]
    last = end - 4  # a uint32 is readable at offsets <= last
    max_hyp = (end - p) // (8 * 44) + 1
    spans = np.empty((n, 2), np.int64)
    bbox_at = np.empty(n, np.int64)
    id_at = np.empty(n, np.int64)
    id_len = np.empty(n, np.int64)
    hyp_off = np.zeros(n + 1, np.int64)
    cls_at = np.empty(max_hyp, np.int64)
    cls_len = np.empty(max_hyp, np.int64)
    codes = np.empty(max_hyp, np.int64)
    first_at = np.empty(_MAX_CLASSES, np.int64)
    first_len = np.empty(_MAX_CLASSES, np.int64)
    nothing = np.empty(0, np.int64)
    h = 0
    for d in range(n):
        p += -p % 4
        start = p
        if p + 8 > last:
            return 0, spans, bbox_at, id_at, id_len, hyp_off, nothing, nothing, nothing, nothing
        p += 12 + _u32(raw, p + 8)
        p += -p % 4
        if p > last:
            return 0, spans, bbox_at, id_at, id_len, hyp_off, nothing, nothing, nothing, nothing
        k = _u32(raw, p)
        spans[d, 0] = start
        spans[d, 1] = p
        p += 4
        if h + k > max_hyp:
            return 0, spans, bbox_at, id_at, id_len, hyp_off, nothing, nothing, nothing, nothing
        for _ in range(k):
            if p > last:
                return (0, spans, bbox_at, id_at, id_len, hyp_off, nothing, nothing, nothing,
                        nothing)
            length = _u32(raw, p)
            cls_at[h] = p
            cls_len[h] = length
            h += 1
            q = p + 4 + length
            p = q + (-(q - 4) % 8) + 8 * 44
        hyp_off[d + 1] = h
        p += -(p - 4) % 8
        bbox_at[d] = p
        p += 80
        p += -p % 4
        if p > last:
            return 0, spans, bbox_at, id_at, id_len, hyp_off, nothing, nothing, nothing, nothing
        id_at[d] = p
        id_len[d] = _u32(raw, p)
        p += 4 + id_len[d]
    if p > end:
        return 0, spans, bbox_at, id_at, id_len, hyp_off, nothing, nothing, nothing, nothing
    # every string lies before p <= end: its bytes are readable
    n_names = 0
    for j in range(h):
        a, length = cls_at[j] + 4, cls_len[j]
        code = -1
        for c in range(n_names):
            if first_len[c] != length:
                continue
            b = first_at[c] + 4
            same = True
            for i in range(length - 1):
                if raw[a + i] != raw[b + i]:
                    same = False
                    break
            if same:
                code = c
                break
        if code < 0:
            if n_names == _MAX_CLASSES:
                return (2, spans, bbox_at, id_at, id_len, hyp_off, cls_at[:h], cls_len[:h],
                        nothing, nothing)
            code = n_names
            first_at[code] = cls_at[j]
            first_len[code] = length
            n_names += 1
        codes[j] = code
    return (1, spans, bbox_at, id_at, id_len, hyp_off, cls_at[:h], cls_len[:h], codes[:h],
            first_at[:n_names])


@njit(inline="always")
def _aligned(p, k):
    """Offset ``p`` moved up to a multiple of ``k`` relative to byte 4 (the end of the
    encapsulation header, where CDR alignment starts)."""
    return p + (-(p - 4)) % k


@njit(inline="always")
def _f64(raw, at, scratch):
    """The little-endian float64 at byte ``at`` (its bits through ``scratch``, one uint64
    whose float64 view is read: NaN payloads kept, any host byte order)."""
    bits = np.uint64(0)
    for b in range(8):
        bits |= np.uint64(raw[at + b]) << np.uint64(8 * b)
    scratch[0] = bits
    return scratch.view(np.float64)[0]


_I64 = array_in(types.int64)


@njit(types.Tuple((array_out(types.float64, 2), array_out(types.int64), array_out(types.float64),
                   array_out(types.int64)))(_U8, _I64, _I64, _I64, _I64),
      cache=True, nogil=True)
def _fields(raw, bbox_at, cls_at, cls_len, hyp_off):
    """The fixed-size fields at the offsets ``_walk`` found, in one pass: per detection
    its centre, size and quaternion (n, 10: the order ``boxes.arrays_from_fields``
    takes); per hypothesis the offset of its score (the string's end, 8-aligned relative
    to byte 4), the score and the owning detection."""
    n, h = bbox_at.shape[0], cls_at.shape[0]
    scratch = np.empty(1, np.uint64)
    box = np.empty((n, 10))
    for i in range(n):
        a = bbox_at[i]  # centre position (3), orientation (4), size (3)
        for k in range(3):
            box[i, k] = _f64(raw, a + 8 * k, scratch)
            box[i, 3 + k] = _f64(raw, a + 56 + 8 * k, scratch)
        for k in range(4):
            box[i, 6 + k] = _f64(raw, a + 24 + 8 * k, scratch)
    score_at = np.empty(h, np.int64)
    score = np.empty(h)
    for j in range(h):
        score_at[j] = _aligned(cls_at[j] + 4 + cls_len[j], 8)
        score[j] = _f64(raw, score_at[j], scratch)
    det = np.empty(h, np.int64)
    for i in range(n):
        det[hyp_off[i]:hyp_off[i + 1]] = i
    return box, score_at, score, det


@njit(array_out(types.uint8)(_U8, _I64, _I64), cache=True, nogil=True)
def _joined(raw, start, size):
    # the ``size`` bytes at each ``start``, one NUL between each two
    n = len(start)
    total = n - 1
    for i in range(n):
        total += size[i]
    out = np.empty(max(total, 0), np.uint8)
    p = 0
    for i in range(n):
        m = size[i]
        out[p:p + m] = raw[start[i]:start[i] + m]
        p += m
        if i + 1 < n:
            out[p] = 0
            p += 1
    return out


def joined_strings(buf, start, size, what: str) -> list:
    """The UTF-8 strings of ``size[k]`` bytes at ``start[k]`` of ``buf`` (ids of a
    message's entries): gathered into one buffer by a compiled pass and decoded at once
    instead of a slice and a decode each (an LMD frame's 50 detections and 500
    proposals decoded in 0.26 instead of 0.34 ms); a string with a NUL in it or bytes
    that are not UTF-8 go one by one (``CdrError`` naming ``what``)."""
    if len(start) == 0:
        return []
    start = np.asarray(start, np.int64)
    size = np.asarray(size, np.int64)
    return _split_joined(_joined(np.frombuffer(buf, np.uint8), start, size), buf, start, size,
                         what)


def _split_joined(joined: np.ndarray, buf, start, size, what: str) -> list:
    """:func:`joined_strings` from the joined bytes (``_joined``)."""
    n = len(start)
    if n == 0:
        return []
    try:
        text = joined.tobytes().decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is not None and text.count("\0") == n - 1:
        return text.split("\0")
    return decoded_strings([buf[a:a + m] for a, m in zip(np.asarray(start).tolist(),
                                                         np.asarray(size).tolist())], what)


def decoded_strings(items: list, what: str) -> list:
    """``items`` (bytes) decoded as UTF-8; ``CdrError`` naming ``what`` for one that is not."""
    try:
        return [b.decode("utf-8") for b in items]
    except UnicodeDecodeError as exc:
        raise CdrError(f"{what} is not UTF-8: {exc}") from None


@njit((_U8, types.int64, types.int64), cache=True, nogil=True)
def _decode(raw, p, n):
    """The usual message in one compiled call: ``_walk``, ``_fields``, the ids
    (``_joined``), the hypothesis rules (``boxes.hypothesis_table``) and the terms of the
    orientation angles (``boxes.rpy_terms``). One call instead of five: each call costs
    15-20 us more when the caches are cold, as in a node between frames. ``good`` False
    (then every array is empty or partial): bytes the walk cannot follow, more distinct
    class names than it groups, or a string of length 0; the caller then takes the
    step-by-step path, which says why."""
    ok, spans, bbox_at, id_at, id_len, hyp_off, cls_at, cls_len, codes, first_at = _walk(
        raw, p, n)
    good = ok == 1
    if good:
        for d in range(n):
            good &= id_len[d] > 0
        for j in range(cls_len.shape[0]):
            good &= cls_len[j] > 0
    k = n if good else 0
    h = cls_at.shape[0] if good else 0
    box, score_at, score, det = _fields(raw, bbox_at[:k], cls_at[:h], cls_len[:h],
                                        hyp_off[:k + 1])
    ids = _joined(raw, id_at[:k] + 4, id_len[:k] - 1)
    m = first_at.shape[0] if good else 0
    name_empty = np.empty(m, np.bool_)
    for c in range(m):
        name_empty[c] = _u32(raw, first_at[c]) == 1   # the NUL alone
    scores, top, cls, flags = hypothesis_table(box, det, codes[:h].copy(), score, name_empty)
    num, den, sine = rpy_terms(box[:, 6:10])
    return (good, spans, bbox_at, id_at, id_len, hyp_off, cls_at, score_at, score, det,
            first_at, box, ids, scores, top, cls, flags, num, den, sine)


def decode_detection_array(data) -> DecodedDetections:
    """Decode serialized Detection3DArray bytes (``CdrError`` when they are not one)."""
    # a Detection3D takes > 100 bytes
    buf, _, h, n, p = open_array(data, "Detection3DArray", "detections", 100, words=False)
    e = "<"
    f = _FMTS[e]
    raw_bytes = np.frombuffer(buf, dtype=np.uint8)
    (good, spans, bbox_at, id_at, id_len, hyp_off, cls_at, score_at, hyp_sc, hyp_det, first_at,
     raw, joined, scores, top, cls, flags, num, den, sine) = _decode(raw_bytes, p, n)
    if good:
        ids = _split_joined(joined, buf, id_at + 4, id_len - 1, "an id")
        u32 = f.u32
        names = [read_string(buf, a, u32, len(buf))[0] for a in first_at.tolist()]
        rpy = rpy_angles(num, den, sine)
        return DecodedDetections(
            header=h, arrays=arrays_from_table(raw, ids, names, scores, top, cls, flags, rpy),
            data=buf, endian=e, det_spans=spans, bbox_at=bbox_at, id_at=id_at,
            hyp_offsets=hyp_off, hyp_det=hyp_det, hyp_class_at=cls_at, hyp_score_at=score_at,
            hyp_score=hyp_sc)
    ok, spans, bbox_at, id_at, id_len, hyp_off, cls_at, lengths, codes, first_at = _walk(
        raw_bytes, p, n)
    if not ok:  # the loop says where the bytes end
        spans, bbox_at, id_at, ids, hyp_off, cls_at = _layout_loop(buf, _words(buf), p, n)
        id_at = np.asarray(id_at, dtype=np.int64)
        bbox_at = np.asarray(bbox_at, dtype=np.int64)
        cls_at = np.asarray(cls_at, dtype=np.int64)
        hyp_off = np.asarray(hyp_off, dtype=np.int64)
        lengths = _gather(raw_bytes, cls_at, 4).view("<u4").reshape(-1).astype(np.int64)
        id_len = _gather(raw_bytes, id_at, 4).view("<u4").reshape(-1)
    if n and id_len.min() == 0:
        raise CdrError("bad string: an id of length 0")
    ids = (joined_strings(buf, id_at + 4, id_len - 1, "an id") if ok
           else decoded_strings(ids, "an id"))
    if len(lengths) and lengths.min() == 0:
        raise CdrError(f"bad string at byte {int(cls_at[np.argmin(lengths)])}: length 0")
    raw, score_at, hyp_sc, hyp_det = _fields(raw_bytes, bbox_at, cls_at, lengths, hyp_off)
    if ok == 1:
        u32 = f.u32
        names = [read_string(buf, a, u32, len(buf))[0] for a in first_at.tolist()]
    else:
        codes, names = _class_codes(buf, raw_bytes, cls_at, lengths)
    return DecodedDetections(
        header=h, arrays=arrays_from_fields(raw, ids, hyp_det, (codes, names), hyp_sc),
        data=buf, endian=e, det_spans=np.asarray(spans, dtype=np.int64).reshape(n, 2),
        bbox_at=bbox_at, id_at=id_at, hyp_offsets=hyp_off,
        hyp_det=hyp_det, hyp_class_at=cls_at, hyp_score_at=score_at, hyp_score=hyp_sc)


def rescaled_scores(hyp_score, hyp_det, confidence) -> np.ndarray:
    """Hypothesis scores (flat, ``hyp_det`` = detection of each) re-scaled per detection so
    that its top hypothesis equals ``confidence[det]`` and the others keep their ratio to
    it. A top score <= 0 (or none finite) cannot be scaled: the first top hypothesis is set
    to the confidence, the others stay. NaN confidence: every score of the detection NaN."""
    s = np.asarray(hyp_score, dtype=np.float64)
    det = np.asarray(hyp_det, dtype=np.int64)
    conf = np.asarray(confidence, dtype=np.float64)
    top = np.full(len(conf), -np.inf)
    np.fmax.at(top, det, s)  # NaN scores never win
    c, t = conf[det], top[det]
    scalable = (t > 0) & np.isfinite(t)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(scalable, s * (c / t), s)
    is_top = s == t
    out[is_top & scalable] = c[is_top & scalable]  # exact, not c / t * t
    # unscalable detections: their first top hypothesis (or first, if none is finite)
    un = np.flatnonzero(~scalable)
    if len(un):
        first = {}
        for j, d, v, tv in zip(un.tolist(), det[un].tolist(), s[un].tolist(), t[un].tolist()):
            if d not in first or (v == tv and s[first[d]] != tv):
                first[d] = j
        idx = np.fromiter(first.values(), dtype=np.int64, count=len(first))
        out[idx] = conf[det[idx]]
    out[np.isnan(c)] = np.nan
    return out


@njit(inline="always")
def _copy(out, at, raw, start, m):
    """``out[at:at + m] = raw[start:start + m]`` as a loop over the two slices: numba's
    slice assignment costs ~0.5 µs of set-up, a loop over the offsets into the whole
    buffers is not vectorised (measured: 200 hypotheses' 344 bytes 113 / 90 µs, this
    17 µs). The helpers here are inlined: a call to a kernel compiled on its own costs
    ~80 ns."""
    dst, src = out[at:at + m], raw[start:start + m]
    for b in range(m):
        dst[b] = src[b]


@njit(inline="always")
def _copy_string(out, p, raw, at, write):
    """The CDR string entry at ``raw[at]`` (uint32 length, bytes) copied to ``out[p]``
    when ``write``; returns the offset after it."""
    m = 4 + _u32(raw, at)
    if write:
        _copy(out, p, raw, at, m)
    return p + m


@njit(inline="always")
def _put_u32(out, at, value):
    """Write ``value`` as a little-endian uint32 at byte ``at``."""
    for b in range(4):
        out[at + b] = np.uint8((value >> (8 * b)) & 0xFF)


@njit(inline="always")
def _put_f64(out, at, value, scratch):
    """Write ``value`` as a little-endian float64 at byte ``at`` (its bits through
    ``scratch``'s uint64 view, as ``_f64`` reads them)."""
    scratch[0] = value
    bits = scratch.view(np.uint64)[0]
    for b in range(8):
        out[at + b] = np.uint8((bits >> np.uint64(8 * b)) & np.uint64(0xFF))


@njit(array_out(types.uint8)(_U8, _U8, _I64, array_in(types.int64, 2), _I64, _I64, _I64,
                             array_in(types.float64), _I64, _I64),
      cache=True, nogil=True)
def _reencode(raw, opening, rows, spans, hyp_off, cls_at, score_at, score, bbox_at, id_at):
    """``encode_detection_array``'s bytes: ``opening``, then for each of ``rows`` its
    detection copied field by field from ``raw`` (re-aligned: each part is aligned
    relative to byte 4 as it is written) with the hypothesis scores ``score``."""
    size = opening.shape[0]
    for pass_ in range(2):
        write = pass_ == 1
        out = np.zeros(size if write else 0, np.uint8)
        if write:
            _copy(out, 0, opening, 0, opening.shape[0])
        scratch = np.empty(1, np.float64)
        p = opening.shape[0]
        for i in rows:
            p = _aligned(p, 4)
            m = spans[i, 1] - spans[i, 0]  # header: 4-aligned fields only
            if write:
                _copy(out, p, raw, spans[i, 0], m)
            p = _aligned(p + m, 4)
            if write:
                _copy(out, p, raw, spans[i, 1], 4)
            p += 4
            for j in range(hyp_off[i], hyp_off[i + 1]):
                p = _copy_string(out, _aligned(p, 4), raw, cls_at[j], write)
                p = _aligned(p, 8)
                if write:
                    _put_f64(out, p, score[j], scratch)
                    _copy(out, p + 8, raw, score_at[j] + 8, 8 * (_N_HYP_DOUBLES - 1))
                p += 8 * _N_HYP_DOUBLES
            p = _aligned(p, 8)
            if write:
                _copy(out, p, raw, bbox_at[i], 80)
            p = _copy_string(out, _aligned(p + 80, 4), raw, id_at[i], write)
        size = p
    return out


def encode_detection_array(dec: DecodedDetections, rows, hyp_score=None) -> bytes:
    """Serialized Detection3DArray of detections ``rows`` of ``dec`` (in that order), with
    the header of ``dec``, every field copied, and hypothesis scores ``hyp_score`` (flat,
    one per hypothesis of ``dec``; None keeps them)."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    n = len(dec)
    if len(rows) and (rows.min() < 0 or rows.max() >= n):
        raise IndexError(f"rows outside the {n} detections")
    scores = dec.hyp_score if hyp_score is None else np.asarray(hyp_score, dtype=np.float64)
    if scores.shape != dec.hyp_score.shape:
        raise ValueError(f"{scores.shape} hypothesis scores for {dec.hyp_score.shape}")
    opening = np.frombuffer(array_opening(dec.data, len(rows)), np.uint8)
    return _reencode(np.frombuffer(dec.data, np.uint8), opening, rows, dec.det_spans,
                     dec.hyp_offsets, dec.hyp_class_at, dec.hyp_score_at,
                     np.ascontiguousarray(scores), dec.bbox_at, dec.id_at).tobytes()


@njit(array_out(types.uint8)(_U8, _U8, _I64, _U8, _I64, array_in(types.float64, 2),
                             array_in(types.float64, 2), array_in(types.float64, 2),
                             array_in(types.float64, 2)),
      cache=True, nogil=True)
def _write_detections(hdr, names, name_at, ids, id_at, S, boxes, quat, cov):
    """``encode_detections``' bytes: per detection ``hdr``, one hypothesis per finite
    score of its row of ``S`` (class name entry ``names[name_at[c]:name_at[c + 1]]``,
    highest first, ties in column order: numpy's stable argsort), the score, the pose
    (``boxes``' centre, ``quat``) and its covariance (diagonal ``cov[i]``, zeros when
    ``cov`` has no rows), the bbox (centre pose, ``boxes``' size) and its id entry
    ``ids[id_at[i]:id_at[i + 1]]``; two passes (size, then bytes). The hypotheses' order
    and the pose and bbox records are built here too: as numpy steps they were ~15
    calls a frame, each dearer than its arithmetic."""
    n, n_cls = S.shape
    with_cov = cov.shape[0] > 0
    order = np.empty((n, n_cls), np.int64)
    counts = np.zeros(n, np.int64)
    for i in range(n):  # stable insertion of the finite scores, highest first
        m = 0
        for c in range(n_cls):
            v = S[i, c]
            if not np.isfinite(v):
                continue
            at = m
            while at > 0 and S[i, order[i, at - 1]] < v:
                order[i, at] = order[i, at - 1]
                at -= 1
            order[i, at] = c
            m += 1
        counts[i] = m
    # per detection the 43 float64 of a hypothesis' pose and covariance, the 10 of its bbox
    pose_cov = np.zeros((n, 43))
    bbox = np.empty((n, 10))
    for i in range(n):
        for k in range(3):
            pose_cov[i, k] = boxes[i, k]
            bbox[i, 7 + k] = boxes[i, 3 + k]
        for k in range(4):
            pose_cov[i, 3 + k] = quat[i, k]
        if with_cov:
            for k in range(6):
                pose_cov[i, 7 + 7 * k] = cov[i, k]
        for k in range(7):
            bbox[i, k] = pose_cov[i, k]
    pose_bytes = pose_cov.reshape(-1).view(np.uint8)
    bbox_bytes = bbox.reshape(-1).view(np.uint8)
    size = 0
    for pass_ in range(2):
        write = pass_ == 1
        out = np.zeros(size if write else 0, np.uint8)
        scratch = np.empty(1, np.float64)
        if write:
            out[1] = 1  # encapsulation: plain CDR, little-endian
            _copy(out, 4, hdr, 0, hdr.shape[0])
        p = 4 + hdr.shape[0]
        if write:
            _put_u32(out, p, n)
        p += 4
        for i in range(n):
            p = _aligned(p, 4)
            if write:
                _copy(out, p, hdr, 0, hdr.shape[0])
            p += hdr.shape[0]
            if write:
                _put_u32(out, p, counts[i])
            p += 4
            for k in range(counts[i]):
                c = order[i, k]
                p = _aligned(p, 4)
                m = name_at[c + 1] - name_at[c]
                if write:
                    _copy(out, p, names, name_at[c], m)
                p = _aligned(p + m, 8)
                if write:
                    _put_f64(out, p, S[i, c], scratch)
                    _copy(out, p + 8, pose_bytes, 344 * i, 344)
                p += 352
            p = _aligned(p, 8)
            if write:
                _copy(out, p, bbox_bytes, 80 * i, 80)
            p += 80  # 80 bytes after an 8-aligned offset: the id's count is 4-aligned
            m = id_at[i + 1] - id_at[i]
            if write:
                _copy(out, p, ids, id_at[i], m)
            p += m
        size = p
    return out


_NO_COVARIANCE = np.zeros((0, 6))  # encode_detections without a covariance
_NAME_STRINGS: dict = {}  # class names -> their cdr_strings, read-only (encode_detections)


def _name_strings(class_names) -> tuple[np.ndarray, np.ndarray]:
    """``cdr_strings(class_names)``, kept: a node encodes the same few names every frame."""
    key = tuple(class_names)
    got = _NAME_STRINGS.get(key)
    if got is None:
        if len(_NAME_STRINGS) >= 16:
            _NAME_STRINGS.clear()
        got = cdr_strings(key)
        for a in got:
            a.flags.writeable = False
        _NAME_STRINGS[key] = got
    return got


def encode_detections(header, boxes, class_names, class_scores, *, ids=None,
                      covariance_diagonal=None) -> bytes:
    """Serialized (little-endian CDR) Detection3DArray of new boxes: the message
    ``boxes.arrays_to_detections(header, boxes, None, None, ids=ids, class_scores=
    {class_names[c]: class_scores[:, c]}, covariance_diagonal=...)`` would serialize to
    (padding bytes aside, which rclpy leaves uninitialized), without building it and
    having rclpy convert it (~3.5 ms for 60 boxes x 4 classes, this ~0.7 ms). One
    hypothesis per finite score, highest first (ties: column order). ``boxes`` (N, 7),
    ``class_scores`` (N, C), ``covariance_diagonal`` (N, 6) or None."""
    f = _FMTS["<"]
    b = np.ascontiguousarray(boxes, dtype=np.float64).reshape(-1, 7)
    n = len(b)
    S = np.ascontiguousarray(class_scores, dtype=np.float64).reshape(n, len(class_names))
    cov = (_NO_COVARIANCE if covariance_diagonal is None else
           np.ascontiguousarray(covariance_diagonal, dtype=np.float64).reshape(n, 6))
    frame = header.frame_id.encode() + b"\0"
    hdr = f.stamp.pack(header.stamp.sec, header.stamp.nanosec) + f.u32.pack(len(frame)) + frame
    hdr += b"\0" * (-len(hdr) % 4)  # the next field (a uint32) is 4-aligned
    names, name_at = _name_strings(class_names)
    id_bytes, id_at = cdr_strings(range(n) if ids is None else ids)
    return _write_detections(np.frombuffer(hdr, np.uint8), names, name_at, id_bytes, id_at,
                             S, b, yaw_to_quaternion(b[:, 6]), cov).tobytes()
