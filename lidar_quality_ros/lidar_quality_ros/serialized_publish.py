"""Serialized messages published from the caller's own buffer (rcl's C API through ctypes).

Why: rclpy publishes serialized bytes (``Publisher.publish(bytes)``) by copying them into
a ``std::string`` first, and a message object by converting it to the C message (its
``data`` copied) that the rmw then serializes (copied again). The nodes write their
outputs as CDR bytes (``detection_cdr``, ``segment_quality_cdr``, LMS's output cloud:
3.1 MB a 120k-point frame); here ``rcl_publish_serialized_message`` reads them where they
are, and the rmw's own copy into the middleware is the only one. Measured: publishing
LMS's 3.1 MB output cloud to a subscriber in another process cost 1.24 ms of the
publishing thread's CPU as a message, 1.15 as bytes through rclpy, 0.99 from the buffer.

Any contiguous bytes-like object works (``bytes``, ``bytearray``, ``memoryview``, a 1-D
uint8 numpy array). Where the C functions cannot be loaded (:mod:`~lidar_quality_ros.rcl_api`),
rclpy publishes the bytes as before.
"""
from __future__ import annotations

import ctypes

import numpy as np

from . import rcl_api

__all__ = ["publish_serialized", "is_serialized"]

_BYTES_LIKE = (bytes, bytearray, memoryview, np.ndarray)


def is_serialized(msg) -> bool:
    """Whether ``msg`` is a serialized message (bytes-like) rather than a message object."""
    return isinstance(msg, _BYTES_LIKE)


def publish_serialized(publisher, data) -> None:
    """Publish the serialized message ``data`` (CDR bytes of ``publisher``'s type, as
    rclpy's ``publish(bytes)`` takes them) without copying it; errors as rclpy's."""
    api = rcl_api.load()
    if api is None:
        publisher.publish(data if isinstance(data, bytes) else bytes(data))
        return
    view = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data
    if view.dtype != np.uint8 or view.ndim != 1 or not view.flags.c_contiguous:
        raise TypeError(f"serialized message must be contiguous bytes, got {view.dtype} "
                        f"{view.shape}")
    msg = rcl_api.Serialized()
    msg.buffer = ctypes.cast(view.ctypes.data, ctypes.POINTER(ctypes.c_uint8))
    msg.buffer_length = msg.buffer_capacity = len(view)
    msg.allocator = api.allocator()  # never used: rcl reads the buffer and copies it
    handle = publisher.handle
    with handle:
        ret = api.publish(handle.pointer, ctypes.byref(msg), None)
    if ret != 0:
        raise rcl_api.rcl_error(f"rcl_publish_serialized_message failed ({ret})")
