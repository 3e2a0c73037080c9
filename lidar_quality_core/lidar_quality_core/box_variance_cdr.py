"""lidar_quality_msgs/BoxVarianceArray read from its CDR bytes.

Why: rclpy builds one BoxVariance object per entry (~2 µs each plus the conversion); a
100-box head's variances took ~0.2 ms to deserialize, twice per mimo_node frame. Read
here they take one loop over the entries (offsets) and one gather.

Layout (plain little-endian CDR, ``00 01``; alignment relative to byte 4): header (stamp,
frame_id), entry count; per entry: detection_index uint32, detection_id string, then x,
y, z, length, width, height, yaw float64 (8-aligned). Other bytes raise
:class:`~.detection_cdr.CdrError`.
"""
from __future__ import annotations

import struct
import sys
from dataclasses import dataclass

import numpy as np

from .detection_cdr import CdrError, _gather, _string

__all__ = ["DecodedVariances", "decode_box_variance_array"]

_U32 = struct.Struct("<I")


@dataclass
class DecodedVariances:
    """A decoded BoxVarianceArray: ``header``, per entry ``index`` (detection_index),
    ``ids`` (detection_id) and ``values`` (n, 7): x, y, z, length, width, height, yaw."""

    header: object
    index: np.ndarray
    ids: list
    values: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def decode_box_variance_array(data) -> DecodedVariances:
    """Decode serialized BoxVarianceArray bytes (``CdrError`` when they are not one)."""
    from std_msgs.msg import Header

    buf = bytes(data)
    end = len(buf)
    if end < 4 or buf[:2] != b"\x00\x01":
        raise CdrError(f"unsupported encapsulation {buf[:4].hex() or '(empty)'} "
                       "(plain little-endian CDR expected: 0001)")
    words = (memoryview(buf)[:end - end % 4].cast("I") if sys.byteorder == "little"
             else np.frombuffer(buf, "<u4", count=end // 4).tolist())
    index, ids, values_at = [], [], []
    try:
        sec, nsec = struct.unpack_from("<iI", buf, 4)
        frame_id, p = _string(buf, 12, _U32, end)
        p += -p % 4
        n = words[p >> 2]
        p += 4
        if n > (end - p) // 64:  # an entry takes >= 64 bytes
            raise CdrError(f"{n} variance entries cannot fit in {end} bytes")
        for _ in range(n):
            p += -p % 4
            index.append(words[p >> 2])
            q = p + 8 + words[(p + 4) >> 2]
            if q > end:
                raise CdrError(f"bad string at byte {p + 4}")
            ids.append(buf[p + 8:q - 1])
            p = q + (-(q - 4) % 8)
            values_at.append(p)
            p += 56
    except (IndexError, struct.error) as exc:
        raise CdrError(f"truncated BoxVarianceArray ({end} bytes): {exc}") from None
    if p > end:
        raise CdrError(f"truncated BoxVarianceArray: {end} bytes, need {p}")
    try:
        ids = [b.decode("utf-8") for b in ids]
    except UnicodeDecodeError as exc:
        raise CdrError(f"a detection_id is not UTF-8: {exc}") from None
    at = np.asarray(values_at, dtype=np.int64)
    values = _gather(np.frombuffer(buf, np.uint8), at, 56).view("<f8").reshape(n, 7)
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, nsec
    return DecodedVariances(h, np.asarray(index, dtype=np.int64), ids,
                            values.astype(np.float64))
