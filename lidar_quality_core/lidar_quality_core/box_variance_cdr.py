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

from dataclasses import dataclass

import numpy as np

from .detection_cdr import CdrError, _gather, open_array

__all__ = ["DecodedVariances", "decode_box_variance_array"]


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
    # an entry takes >= 64 bytes
    buf, words, h, n, p = open_array(data, "BoxVarianceArray", "variance entries", 64)
    end = len(buf)
    index, ids, values_at = [], [], []
    try:
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
    except IndexError as exc:
        raise CdrError(f"truncated BoxVarianceArray ({end} bytes): {exc}") from None
    if p > end:
        raise CdrError(f"truncated BoxVarianceArray: {end} bytes, need {p}")
    try:
        ids = [b.decode("utf-8") for b in ids]
    except UnicodeDecodeError as exc:
        raise CdrError(f"a detection_id is not UTF-8: {exc}") from None
    at = np.asarray(values_at, dtype=np.int64)
    values = _gather(np.frombuffer(buf, np.uint8), at, 56).view("<f8").reshape(n, 7)
    return DecodedVariances(h, np.asarray(index, dtype=np.int64), ids,
                            values.astype(np.float64))
