"""autoware_perception_msgs/DetectedObjects read from and written to its CDR bytes.

Why: rclpy builds one Python object per nested message, about 70 µs per DetectedObject
here (a pose and a twist with their 36-element covariances each); the demo's LMD frame with
~510 objects spent ~37 ms of CPU on it. The nodes subscribe raw and read the bytes here
(~1 ms), the same way ``detection_cdr`` reads Detection3DArray, and lmd_node writes its
re-scored output as bytes.

Layout (plain little-endian CDR, ``00 01``; alignment relative to byte 4): header (stamp,
frame_id), object count; per object: existence_probability float32; classification count
and elements (label uint8, 3 padding bytes, probability float32: 8 bytes each);
pose_with_covariance (43 float64, 8-aligned), has_position_covariance, orientation_
availability; twist_with_covariance (42 float64, 8-aligned), has_twist,
has_twist_covariance; shape: type uint8, footprint (count, Point32 x 12 bytes, 4-aligned),
dimensions (3 float64, 8-aligned). Other bytes raise :class:`~.detection_cdr.CdrError`.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .autoware_objects import POLYGON, arrays_of_objects, label_names, scored_values
from .boxes import DetectionArrays
from .detection_cdr import _PAD, CdrError, _gather, array_opening, open_array

__all__ = ["DecodedObjects", "decode_detected_objects", "encode_detected_objects"]

_U32 = struct.Struct("<I")
_F32 = struct.Struct("<f")
_POSE = 43 * 8     # pose (7) + covariance (36) float64
_TWIST = 42 * 8    # twist (6) + covariance (36) float64


@dataclass
class DecodedObjects:
    """A decoded DetectedObjects: ``header``, ``arrays`` (as ``autoware_objects.
    objects_to_arrays``), ``existence`` (n,) and where each part sits in ``data`` (for
    :func:`encode_detected_objects`). Classifications are flat, grouped by object: object
    ``i`` owns ``cls_offsets[i]:cls_offsets[i + 1]``."""

    header: object
    arrays: DetectionArrays
    data: bytes
    existence: np.ndarray    # (n,) float64 of the float32 field
    exist_at: np.ndarray     # (n,) offset of existence_probability
    cls_offsets: np.ndarray  # (n + 1,) CSR
    cls_at: np.ndarray       # (H,) offset of each element's label
    cls_prob: np.ndarray     # (H,) float64 of the float32 probabilities
    pose_at: np.ndarray      # (n,) offset of the pose (then covariance, flags)
    twist_at: np.ndarray     # (n,) offset of the twist (then covariance, flags)
    type_at: np.ndarray      # (n,) offset of the shape type
    fp_at: np.ndarray        # (n,) offset of the footprint point count
    dims_at: np.ndarray      # (n,) offset of the dimensions

    def __len__(self) -> int:
        return len(self.exist_at)


def decode_detected_objects(data, class_map: dict[str, str] | None = None) -> DecodedObjects:
    """Decode serialized DetectedObjects bytes (``CdrError`` when they are not one)."""
    # a DetectedObject takes > 720 bytes
    buf, words, h, n, p = open_array(data, "DetectedObjects", "objects", 720)
    end = len(buf)
    exist_at, cls_off, pose_at, twist_at, type_at, fp_at, dims_at = [], [0], [], [], [], [], []
    try:
        n_cls = 0
        # offsets only, one iteration per object; the fields are gathered afterwards
        for _ in range(n):
            p += -p % 4
            exist_at.append(p)
            k = words[(p + 4) >> 2]
            n_cls += k
            cls_off.append(n_cls)
            p += 8 + 8 * k
            p += -(p - 4) % 8
            pose_at.append(p)
            p += _POSE + 2
            p += -(p - 4) % 8
            twist_at.append(p)
            p += _TWIST + 2
            type_at.append(p)
            p += 1
            p += -p % 4
            fp_at.append(p)
            p += 4 + 12 * words[p >> 2]
            p += -(p - 4) % 8
            dims_at.append(p)
            p += 24
    except (IndexError, struct.error) as exc:
        raise CdrError(f"truncated DetectedObjects ({end} bytes): {exc}") from None
    if p > end:
        raise CdrError(f"truncated DetectedObjects: {end} bytes, need {p}")
    raw_bytes = np.frombuffer(buf, dtype=np.uint8)
    exist_at, pose_at, twist_at, type_at, fp_at, dims_at, cls_off = (
        np.asarray(x, dtype=np.int64)
        for x in (exist_at, pose_at, twist_at, type_at, fp_at, dims_at, cls_off))
    det = np.repeat(np.arange(n), np.diff(cls_off))
    first = np.repeat(exist_at + 8, np.diff(cls_off))
    cls_at = first + 8 * (np.arange(len(det)) - np.repeat(cls_off[:-1], np.diff(cls_off)))
    labels = raw_bytes[cls_at] if len(cls_at) else np.zeros(0, np.uint8)
    probs = _gather(raw_bytes, cls_at + 4, 4).view("<f4").reshape(-1).astype(np.float64)
    existence = _gather(raw_bytes, exist_at, 4).view("<f4").reshape(-1).astype(np.float64)
    pose = _gather(raw_bytes, pose_at, 56).view("<f8").reshape(n, 7)
    dims = _gather(raw_bytes, dims_at, 24).view("<f8").reshape(n, 3)
    types = raw_bytes[type_at].astype(np.int64) if n else np.zeros(0, np.int64)
    footprints = {}
    for i in np.flatnonzero(types == POLYGON).tolist():  # polygons only: rare, small
        m = int(words[int(fp_at[i]) >> 2])
        footprints[i] = np.frombuffer(buf, "<f4", count=3 * m,
                                      offset=int(fp_at[i]) + 4).reshape(m, 3)
    names = label_names(class_map)
    arrays = arrays_of_objects(pose, types, dims, footprints, det,
                               [names[c] if c < len(names) else f"label_{c}"
                                for c in labels.tolist()], probs)
    return DecodedObjects(h, arrays, buf, existence, exist_at, cls_off, cls_at, probs,
                          pose_at, twist_at, type_at, fp_at, dims_at)


def encode_detected_objects(dec: DecodedObjects, rows, confidence, *,
                            fallback: float | None = None) -> tuple[bytes, int]:
    """``(bytes, n_fallback)``: serialized DetectedObjects of objects ``rows`` of ``dec``
    (in that order), header and every field copied, scored with ``confidence`` (one per
    object of ``dec``) as ``autoware_objects.score_objects`` does."""
    exist, probs, n_fallback = scored_values(dec.existence, dec.cls_prob,
                                             np.repeat(np.arange(len(dec)),
                                                       np.diff(dec.cls_offsets)),
                                             confidence, fallback)
    buf = dec.data
    rows = np.asarray(rows, dtype=np.int64).reshape(-1).tolist()
    out = array_opening(buf, len(rows))
    off, cls_at, pr = dec.cls_offsets.tolist(), dec.cls_at.tolist(), probs.tolist()
    ex = exist.tolist()
    pose_at, twist_at = dec.pose_at.tolist(), dec.twist_at.tolist()
    type_at, fp_at, dims_at = dec.type_at.tolist(), dec.fp_at.tolist(), dec.dims_at.tolist()
    pack_f = _F32.pack
    for i in rows:
        out += _PAD[-(len(out) - 4) % 4]
        out += pack_f(ex[i])
        out += _U32.pack(off[i + 1] - off[i])
        for j in range(off[i], off[i + 1]):
            out += buf[cls_at[j]:cls_at[j] + 4]  # label and its padding
            out += pack_f(pr[j])
        out += _PAD[-(len(out) - 4) % 8]
        out += buf[pose_at[i]:pose_at[i] + _POSE + 2]
        out += _PAD[-(len(out) - 4) % 8]
        out += buf[twist_at[i]:type_at[i] + 1]  # twist, covariance, flags, shape type
        out += _PAD[-(len(out) - 4) % 4]
        f = fp_at[i]
        out += buf[f:f + 4 + 12 * _U32.unpack_from(buf, f)[0]]
        out += _PAD[-(len(out) - 4) % 8]
        out += buf[dims_at[i]:dims_at[i] + 24]
    return bytes(out), n_fallback
