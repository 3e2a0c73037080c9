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
uint8 numpy array). Messages below :data:`MIN_BYTES`, and all where the C functions
cannot be loaded (:mod:`~lidar_quality_ros.rcl_api`), rclpy publishes as before.
"""
from __future__ import annotations

import ctypes

import numpy as np

from . import rcl_api

__all__ = ["publish_serialized", "is_serialized"]

_BYTES_LIKE = (bytes, bytearray, memoryview, np.ndarray)

#: smaller messages go through rclpy (``publish(bytes)``): its copy of them costs less
#: than the ctypes call's own steps (measured: a 26 kB message 0.08-0.09 ms of the thread's
#: CPU through rclpy, 0.13-0.19 ms through ctypes; 3.1 MB 1.08-1.22 against 0.93-1.0)
MIN_BYTES = 512 * 1024


class _Message(ctypes.Structure):
    """rcl_serialized_message_t with the buffer as an address (rcl_api.Serialized's layout)."""

    _fields_ = [("buffer", ctypes.c_void_p), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", rcl_api.Allocator)]


_call = None


def _publisher_call():
    """``(rcl_publish_serialized_message taking a _Message, the default allocator)``, made
    once (the allocator is never used: rcl reads the buffer and copies it), or None where
    rcl_api cannot load."""
    global _call
    api = rcl_api.load()
    if _call is None and api is not None:
        fn = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(_Message),
                              ctypes.c_void_p)(ctypes.cast(api.publish, ctypes.c_void_p).value)
        _call = (fn, api.allocator())
    return _call


def is_serialized(msg) -> bool:
    """Whether ``msg`` is a serialized message (bytes-like) rather than a message object."""
    return isinstance(msg, _BYTES_LIKE)


def publish_serialized(publisher, data) -> None:
    """Publish the serialized message ``data`` (CDR bytes of ``publisher``'s type, as
    rclpy's ``publish(bytes)`` takes them); from where it is when it is large
    (:data:`MIN_BYTES`), else through rclpy; errors as rclpy's."""
    if type(data) is bytes and len(data) < MIN_BYTES:   # the usual detection arrays
        publisher.publish(data)
        return
    view = data if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    if view.dtype != np.uint8 or view.ndim != 1 or not view.flags.c_contiguous:
        raise TypeError(f"serialized message must be contiguous bytes, got {view.dtype} "
                        f"{view.shape}")
    call = _publisher_call() if len(view) >= MIN_BYTES else None
    if call is None:
        publisher.publish(data if isinstance(data, bytes) else view.tobytes())
        return
    fn, allocator = call
    msg = _Message(view.__array_interface__["data"][0], len(view), len(view), allocator)
    handle = publisher.handle
    with handle:
        ret = fn(handle.pointer, msg, None)
    if ret != 0:
        raise rcl_api.rcl_error(f"rcl_publish_serialized_message failed ({ret})")

