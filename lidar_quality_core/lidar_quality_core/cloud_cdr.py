"""sensor_msgs/PointCloud2 read from its serialized (CDR) bytes, the point data as a view;
and written as such bytes, the point data filled in place (:func:`serialized_cloud`).

Why: rclpy hands a received cloud over as a message whose ``data`` is an ``array.array``
built by two more copies of the point bytes (the rmw's deserialization into the C message,
then a ``bytes`` object and ``array.frombytes`` in the generated conversion). A node that
subscribes with ``raw=True`` gets the serialized bytes (the rmw's one copy) and reads the
cloud here: the few layout fields are parsed, ``data`` is a read-only numpy ``uint8`` view
into those bytes. :mod:`~lidar_quality_core.pointcloud` reads a :class:`DecodedCloud` as it
reads a message.

Format: the 4-byte encapsulation header (plain little-endian CDR, ``00 01``), then header
(stamp sec int32, nanosec uint32, frame_id string), height, width (uint32), fields[]
(name string, offset uint32, datatype uint8, count uint32), is_bigendian (bool),
point_step, row_step (uint32), data (uint8[]: uint32 length and the bytes), is_dense
(bool); primitives aligned to their size relative to byte 4, strings a uint32 length
(including the NUL) and the bytes. Anything else raises
:class:`~lidar_quality_core.detection_cdr.CdrError`. No rclpy; ``std_msgs`` only for the
decoded header.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .boxes import decoded_header
from .detection_cdr import CdrError, read_string
from .quality_array_cdr import cdr_string, pad

__all__ = ["CloudField", "DecodedCloud", "decode_point_cloud", "serialized_cloud"]

_UINTS = {1: struct.Struct("<I"), 3: struct.Struct("<III")}
_STAMP = struct.Struct("<iI")
_MAX_FIELDS = 4096


@dataclass(frozen=True)
class CloudField:
    """A sensor_msgs/PointField as read from the bytes."""

    name: str
    offset: int
    datatype: int
    count: int


@dataclass
class DecodedCloud:
    """A PointCloud2 read by :func:`decode_point_cloud`: the message's fields, ``data`` a
    read-only uint8 view into the serialized bytes (they stay alive with it)."""

    header: object
    height: int
    width: int
    fields: tuple
    is_bigendian: bool
    point_step: int
    row_step: int
    data: np.ndarray
    is_dense: bool


def _u32s(buf: bytes, p: int, end: int, k: int) -> tuple[tuple, int]:
    """``k`` uint32 at ``p`` (aligned first) and the offset after them."""
    p += -(p - 4) % 4
    if p + 4 * k > end:
        raise CdrError(f"truncated PointCloud2 ({end} bytes) at byte {p}")
    return _UINTS[k].unpack_from(buf, p), p + 4 * k


def _string(buf: bytes, p: int, end: int) -> tuple[str, int]:
    return read_string(buf, p + -(p - 4) % 4, _UINTS[1], end)


def _byte(buf: bytes, p: int, end: int) -> int:
    if p >= end:
        raise CdrError(f"truncated PointCloud2 ({end} bytes) at byte {p}")
    return buf[p]


def decode_point_cloud(data) -> DecodedCloud:
    """:class:`DecodedCloud` of a serialized PointCloud2 (``bytes`` as a raw subscription
    or a bag gives them, or a read-only 1-D uint8 array of them such as the views
    ``lidar_quality_ros.serialized_take`` lends: read in place); ``CdrError`` for another
    encapsulation or inconsistent bytes. The sizes are not checked against each other
    here: ``pointcloud`` does that, with the same messages as for a deserialized cloud."""
    if isinstance(data, bytes):
        buf = data
    elif (isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.ndim == 1
          and not data.flags.writeable and data.flags.c_contiguous):
        buf = memoryview(data)  # a read-only view lent by the input reader: read in place
    else:
        buf = bytes(data)  # anything writable is copied: its owner could change it under us
    end = len(buf)
    if end < 4 or buf[:2] != b"\x00\x01":
        raise CdrError(f"unsupported encapsulation {buf[:4].hex() or '(empty)'} "
                       "(plain little-endian CDR expected: 0001)")
    if end < 12:
        raise CdrError(f"truncated PointCloud2 ({end} bytes)")
    sec, nsec = _STAMP.unpack_from(buf, 4)
    frame_id, p = _string(buf, 12, end)
    (height, width, n_fields), p = _u32s(buf, p, end, 3)
    if n_fields > _MAX_FIELDS or n_fields > (end - p) // 13:
        raise CdrError(f"{n_fields} PointFields cannot fit in {end} bytes")
    fields = []
    for _ in range(n_fields):
        name, p = _string(buf, p, end)
        (offset,), p = _u32s(buf, p, end, 1)
        datatype = _byte(buf, p, end)
        (count,), p = _u32s(buf, p + 1, end, 1)
        fields.append(CloudField(name, offset, datatype, count))
    is_big = _byte(buf, p, end) != 0
    (point_step, row_step, n_data), p = _u32s(buf, p + 1, end, 3)
    if n_data > end - p:
        raise CdrError(f"PointCloud2 data of {n_data} bytes cannot fit in {end} bytes")
    points = np.frombuffer(buf, np.uint8, count=n_data, offset=p)
    points.flags.writeable = False  # a view of the received bytes, whoever owns them
    is_dense = _byte(buf, p + n_data, end) != 0
    return DecodedCloud(decoded_header(sec, nsec, frame_id), height, width, tuple(fields),
                        is_big, point_step, row_step, points, is_dense)


def serialized_cloud(header, height: int, width: int, fields, is_bigendian: bool,
                     point_step: int) -> tuple[np.ndarray, np.ndarray]:
    """A serialized PointCloud2 of ``height * width`` points to fill: ``(message, data)``,
    ``message`` the whole uint8 buffer (every field written, ``row_step = point_step *
    width``, ``is_dense`` false: set ``message[-1] = 1`` for a dense cloud) and ``data``
    the writable view of its ``height * width * point_step`` data bytes, not initialised.
    ``header``: stamp and frame_id as a std_msgs/Header has them; ``fields``: (name,
    offset, datatype, count) tuples."""
    out = bytearray(b"\x00\x01\x00\x00")
    out += _STAMP.pack(header.stamp.sec, header.stamp.nanosec)
    out += cdr_string(header.frame_id)
    pad(out, 4)
    out += _UINTS[3].pack(height, width, len(fields))
    for name, offset, datatype, count in fields:
        pad(out, 4)
        out += cdr_string(name)
        pad(out, 4)
        out += _UINTS[1].pack(offset) + bytes((datatype,))
        pad(out, 4)
        out += _UINTS[1].pack(count)
    out += bytes((1 if is_bigendian else 0,))
    n_data = height * width * point_step
    pad(out, 4)
    out += _UINTS[3].pack(point_step, point_step * width, n_data)
    message = np.empty(len(out) + n_data + 1, np.uint8)
    message[:len(out)] = np.frombuffer(out, np.uint8)
    message[-1] = 0
    return message, message[len(out):len(out) + n_data]
