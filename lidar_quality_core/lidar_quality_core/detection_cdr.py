"""vision_msgs/Detection3DArray read from and written to its serialized (CDR) bytes.

Why: rclpy turns a received Detection3DArray into one Python object per nested message,
and each generated ``__init__`` first builds defaults of all its sub-messages. A
reference-detector proposal array (~450 boxes x 4 hypotheses, 0.8 MB) takes 100-300 ms to
deserialize that way, which is 10-20x the whole LMD frame. A node that subscribes with
``raw=True`` (``SyncedInputs(..., raw_decoders=...)``) and decodes here gets the
:class:`~lidar_quality_core.boxes.DetectionArrays` in ~2 ms, and can publish its re-scored
output as bytes (``rclpy`` publishers take serialized messages).

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

from .boxes import DetectionArrays, arrays_from_fields

__all__ = ["CdrError", "DecodedDetections", "decode_detection_array", "encode_detection_array",
           "rescaled_scores", "encode_detections"]

_ENCAPS = {b"\x00\x01": "<"}
_N_HYP_DOUBLES = 44  # score + pose (7) + covariance (36), contiguous and 8-aligned
_PAD = [b"\0" * k for k in range(8)]


class CdrError(ValueError):
    """Serialized bytes that are not a Detection3DArray this module can read."""


class _Fmt:
    def __init__(self, e: str):
        self.u32 = struct.Struct(e + "I")
        self.stamp = struct.Struct(e + "iI")
        self.f64 = struct.Struct(e + "d")
        self.dtype = np.dtype(e + "f8")


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


def _string(buf, p: int, u32, end: int):
    """(str, offset after it) of the CDR string at ``p`` (already aligned)."""
    (length,) = u32.unpack_from(buf, p)
    q = p + 4 + length
    if length == 0 or q > end:
        raise CdrError(f"bad string at byte {p}: length {length}")
    try:
        return buf[p + 4:q - 1].decode("utf-8"), q
    except UnicodeDecodeError as exc:
        raise CdrError(f"string at byte {p} is not UTF-8: {exc}") from None


def open_array(data, what: str, elements: str, min_size: int):
    """``(buf, words, header, n, p)`` of serialized bytes of a ROS message made of a header
    and one sequence (``what``: its type, for errors): the bytes, a uint32 view of them
    indexed by offset / 4, the std_msgs/Header, the sequence length and the offset of its
    first element. ``CdrError`` for another encapsulation, truncated bytes, or more
    ``elements`` than fit at ``min_size`` bytes each."""
    from std_msgs.msg import Header

    buf = bytes(data)
    end = len(buf)
    if _ENCAPS.get(buf[:2]) is None or end < 4:
        raise CdrError(f"unsupported encapsulation {buf[:4].hex() or '(empty)'} "
                       "(plain little-endian CDR expected: 0001)")
    # every uint32 of these layouts sits at a multiple of 4 (aligned relative to byte 4):
    # a uint32 view indexed by offset / 4 is cheaper than struct in the hot loops (a
    # 462-box proposal array decodes in 1.18 instead of 1.32 ms)
    words = (memoryview(buf)[:end - end % 4].cast("I") if sys.byteorder == "little"
             else np.frombuffer(buf, "<u4", count=end // 4).tolist())
    f = _FMTS["<"]
    try:
        sec, nsec = f.stamp.unpack_from(buf, 4)
        frame_id, p = _string(buf, 12, f.u32, end)
        p += -p % 4
        n = words[p >> 2]
    except (struct.error, IndexError) as exc:
        raise CdrError(f"truncated {what} ({end} bytes): {exc}") from None
    p += 4
    if n > (end - p) // min_size:
        raise CdrError(f"{n} {elements} cannot fit in {end} bytes")
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, nsec
    return buf, words, h, n, p


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
        names[rank[g]] = _string(buf, int(at[i]), _FMTS["<"].u32, len(buf))[0]
    return codes, names


def _layout_loop(buf: bytes, words, p: int, n: int):
    """Where each part of the ``n`` detections from offset ``p`` sits: (spans, bbox_at,
    id_at, ids as bytes, hyp_off, cls_at), walking the layout in Python."""
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


#: arrays shorter than this are walked in Python: the vectorized walk costs ~0.05 ms more
#: at any size and saves ~1 us per detection (measured: equal at ~90 detections, 0.27
#: against 0.52 ms at 512)
_VECTORIZED_MIN = 96


def _layout_vectorized(buf: bytes, p: int, n: int):
    """``_layout_loop``'s result (offsets as int64 arrays) without a Python loop over the
    detections, or None where it cannot tell (then the loop decides, errors included).

    Detections are variable-length, so where one starts depends on all before it. But
    producers give every Detection3D the same header (stamp, frame_id) as a rule: the
    candidates are the 4-aligned places where the first detection's stamp and frame_id
    length recur. Each candidate's end is found with array operations (one round per
    hypothesis rank), and the result is taken only if the candidates chain exactly: the
    first is where the sequence starts, each one starts where the one before ends, and
    there are ``n`` of them; then they are the detections the loop would find."""
    end = len(buf)
    words = np.frombuffer(buf, "<u4", count=end // 4)  # a view: int64 only where read
    nw = len(words)
    first = p + (-p % 4)
    fw = first >> 2
    if fw + 3 > nw:
        return None
    w0, w1, w2 = words[fw], words[fw + 1], int(words[fw + 2])
    hit = words[fw:nw - 2] == w0  # from the first detection on (the array's header matches)
    hit[hit] = (words[fw + 1:nw - 1][hit] == w1) & (words[fw + 2:][hit] == w2)
    starts = (np.flatnonzero(hit) + fw) * 4
    if len(starts) != n or starts[0] != first:
        return None

    def at(offsets):  # the uint32 at each offset (all multiples of 4), None past the end
        i = offsets >> 2
        return words[i].astype(np.int64) if len(i) == 0 or int(i.max()) < nw else None

    q = starts + 12 + w2
    counts_at = q + (-q % 4)
    k = at(counts_at)
    if k is None or int(k.max()) > (end - first) // (8 * _N_HYP_DOUBLES):
        return None
    q = counts_at + 4
    kmax = int(k.max())
    cls = np.zeros((n, kmax), dtype=np.int64)
    for j in range(kmax):
        rows = np.flatnonzero(k > j)
        pj = q[rows]
        length = at(pj)
        if length is None:
            return None
        cls[rows, j] = pj
        r = pj + 4 + length
        q[rows] = r + (-(r - 4) % 8) + 8 * _N_HYP_DOUBLES
    bbox_at = q + (-(q - 4) % 8)
    q = bbox_at + 80
    id_at = q + (-q % 4)
    id_len = at(id_at)
    if id_len is None:
        return None
    ends = id_at + 4 + id_len
    if np.any(ends[:-1] + (-ends[:-1] % 4) != starts[1:]) or int(ends[-1]) > end:
        return None
    ids = [buf[a + 4:a + 3 + m] for a, m in zip(id_at.tolist(), id_len.tolist())]
    hyp_off = np.concatenate([[0], np.cumsum(k)])
    cls_at = cls[np.arange(kmax)[None, :] < k[:, None]]
    return np.column_stack([starts, counts_at]), bbox_at, id_at, ids, hyp_off, cls_at


def decode_detection_array(data) -> DecodedDetections:
    """Decode serialized Detection3DArray bytes (``CdrError`` when they are not one)."""
    # a Detection3D takes > 100 bytes
    buf, words, h, n, p = open_array(data, "Detection3DArray", "detections", 100)
    e = "<"
    f = _FMTS[e]
    layout = _layout_vectorized(buf, p, n) if n >= _VECTORIZED_MIN else None
    if layout is None:
        layout = _layout_loop(buf, words, p, n)
    spans, bbox_at, id_at, ids, hyp_off, cls_at = layout
    id_at = np.asarray(id_at, dtype=np.int64)
    if n and np.any(_gather(np.frombuffer(buf, np.uint8), id_at, 4).view("<u4") == 0):
        raise CdrError("bad string: an id of length 0")
    try:
        ids = [b.decode("utf-8") for b in ids]
    except UnicodeDecodeError as exc:
        raise CdrError(f"an id is not UTF-8: {exc}") from None
    raw_bytes = np.frombuffer(buf, dtype=np.uint8)
    bbox_at = np.asarray(bbox_at, dtype=np.int64)
    cls_at = np.asarray(cls_at, dtype=np.int64)
    hyp_off = np.asarray(hyp_off, dtype=np.int64)
    lengths = _gather(raw_bytes, cls_at, 4).view(f.u32.format[0] + "u4").reshape(-1)
    lengths = lengths.astype(np.int64)
    if len(lengths) and lengths.min() == 0:
        raise CdrError(f"bad string at byte {int(cls_at[np.argmin(lengths)])}: length 0")
    q = cls_at + 4 + lengths
    score_at = q + (-(q - 4) % 8)
    hyp_sc = _gather(raw_bytes, score_at, 8).view(f.dtype).reshape(-1).astype(np.float64)
    codes, names = _class_codes(buf, raw_bytes, cls_at, lengths)
    # centre position (3), orientation (4), size (3) -> centre, size, quaternion
    bb = _gather(raw_bytes, bbox_at, 80).view(f.dtype).reshape(n, 10).astype(np.float64)
    raw = np.concatenate([bb[:, :3], bb[:, 7:10], bb[:, 3:7]], axis=1)
    hyp_det = np.repeat(np.arange(n), np.diff(hyp_off))
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


def encode_detection_array(dec: DecodedDetections, rows, hyp_score=None) -> bytes:
    """Serialized Detection3DArray of detections ``rows`` of ``dec`` (in that order), with
    the header of ``dec``, every field copied, and hypothesis scores ``hyp_score`` (flat,
    one per hypothesis of ``dec``; None keeps them)."""
    buf, f = dec.data, _FMTS[dec.endian]
    pack_d = f.f64.pack
    rows = np.asarray(rows, dtype=np.int64).reshape(-1).tolist()
    out = array_opening(buf, len(rows))
    scores = dec.hyp_score if hyp_score is None else np.asarray(hyp_score, dtype=np.float64)
    off = dec.hyp_offsets.tolist()
    cls_at, score_at = dec.hyp_class_at.tolist(), dec.hyp_score_at.tolist()
    sc = scores.tolist()
    spans, bbox_at, id_at = dec.det_spans.tolist(), dec.bbox_at.tolist(), dec.id_at.tolist()
    u32 = f.u32
    for i in rows:
        start, count_at = spans[i]
        out += _PAD[-(len(out) - 4) % 4]
        out += buf[start:count_at]  # header: 4-aligned fields only
        out += _PAD[-(len(out) - 4) % 4]
        out += buf[count_at:count_at + 4]
        for j in range(off[i], off[i + 1]):
            out += _PAD[-(len(out) - 4) % 4]
            c = cls_at[j]
            out += buf[c:c + 4 + u32.unpack_from(buf, c)[0]]
            out += _PAD[-(len(out) - 4) % 8]
            out += pack_d(sc[j])
            s = score_at[j] + 8
            out += buf[s:s + 8 * (_N_HYP_DOUBLES - 1)]
        out += _PAD[-(len(out) - 4) % 8]
        out += buf[bbox_at[i]:bbox_at[i] + 80]
        out += _PAD[-(len(out) - 4) % 4]
        a = id_at[i]
        out += buf[a:a + 4 + u32.unpack_from(buf, a)[0]]
    return bytes(out)


def encode_detections(header, boxes, class_names, class_scores, *, ids=None,
                      covariance_diagonal=None) -> bytes:
    """Serialized (little-endian CDR) Detection3DArray of new boxes: the message
    ``boxes.arrays_to_detections(header, boxes, None, None, ids=ids, class_scores=
    {class_names[c]: class_scores[:, c]}, covariance_diagonal=...)`` would serialize to
    (padding bytes aside, which rclpy leaves uninitialized), without building it and
    having rclpy convert it (~3.5 ms for 60 boxes x 4 classes, this ~0.7 ms). One
    hypothesis per finite score, highest first (ties: column order). ``boxes`` (N, 7),
    ``class_scores`` (N, C), ``covariance_diagonal`` (N, 6) or None."""
    from .boxes import yaw_to_quaternion

    f = _FMTS["<"]
    u32 = f.u32.pack
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    n = len(b)
    S = np.asarray(class_scores, dtype=np.float64).reshape(n, len(class_names))
    fin = np.isfinite(S)
    order = np.argsort(-np.where(fin, S, -np.inf), axis=1, kind="stable")
    counts = fin.sum(axis=1).tolist()
    quat = yaw_to_quaternion(b[:, 6])
    pose = np.concatenate([b[:, :3], quat], axis=1)
    cov = np.zeros((n, 36))
    if covariance_diagonal is not None:
        cov[:, ::7] = np.asarray(covariance_diagonal, dtype=np.float64).reshape(n, 6)
    # per detection: the pose + covariance bytes of its hypotheses, its bbox bytes
    pose_cov = np.concatenate([pose, cov], axis=1).astype("<f8").tobytes()
    bbox = np.concatenate([pose, b[:, 3:6]], axis=1).astype("<f8").tobytes()
    names = [u32(len(c.encode()) + 1) + c.encode() + b"\0" for c in class_names]
    frame = header.frame_id.encode() + b"\0"
    hdr = f.stamp.pack(header.stamp.sec, header.stamp.nanosec) + u32(len(frame)) + frame
    hdr += b"\0" * (-len(hdr) % 4)  # the next field (a uint32) is 4-aligned
    out = bytearray(b"\x00\x01\x00\x00")
    out += hdr
    out += u32(n)
    ids = [str(i) for i in range(n)] if ids is None else [str(i) for i in ids]
    pack_d = f.f64.pack
    sc, od = S.tolist(), order.tolist()
    for i in range(n):
        out += b"\0" * (-(len(out) - 4) % 4)
        out += hdr
        out += u32(counts[i])
        pc = pose_cov[i * 344:(i + 1) * 344]
        for c in od[i][:counts[i]]:
            out += b"\0" * (-(len(out) - 4) % 4)
            out += names[c]
            out += b"\0" * (-(len(out) - 4) % 8)
            out += pack_d(sc[i][c])
            out += pc
        out += b"\0" * (-(len(out) - 4) % 8)
        out += bbox[i * 80:(i + 1) * 80]
        did = ids[i].encode() + b"\0"
        out += u32(len(did)) + did  # 80 bytes after an 8-aligned offset: 4-aligned
    return bytes(out)
