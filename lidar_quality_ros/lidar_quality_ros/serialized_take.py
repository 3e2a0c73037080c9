"""Serialized messages taken into buffers the node keeps (rcl's C API through ctypes).

Why: rclpy's raw take (``take_message(..., raw=True)``) lets the rmw copy a message twice
(its history's payload into a CDR buffer, that into a serialized message allocated for the
call), then copies it a third time into a new ``bytes`` object and frees the second. For a
120k-point cloud (2-9 MB) the copies are most of an input thread's CPU: measured with
``perf`` in lmd_node at 10 Hz beside the other two nodes, 1.7 ms a frame of memmove for
a 2.8 MB frame. Here ``rcl_take_serialized_message`` writes into a serialized message that
stays ours between takes (grown once to the largest message seen), and the message is
handed over as a read-only numpy view of it: one copy fewer per message, and no
allocation (the C functions: :mod:`~lidar_quality_ros.rcl_api`).

A buffer is lent out with the view and reused only once nothing refers to the view any
more (a weak reference to it tells: views of the view keep it alive). At most
``max_buffers`` are lent at a time; a message that finds none free is taken by rclpy
(bytes, as before), so a node that holds many frames costs memory only up to that bound.

Linux and an rmw with serialized takes (every ROS 2 rmw) only; :func:`available` says
why not elsewhere, and the caller then keeps rclpy's take.
"""
from __future__ import annotations

import ctypes
import weakref

import numpy as np

from . import rcl_api

__all__ = ["BufferTaker", "available"]


def available() -> tuple[bool, str]:
    """``(True, "")`` if messages can be taken here, else ``(False, why not)``."""
    return (True, "") if rcl_api.load() is not None else (False, rcl_api.why_not())


class _Buffer:
    __slots__ = ("msg", "lent")

    def __init__(self, msg: rcl_api.Serialized):
        self.msg = msg
        self.lent = None  # weak reference to the view handed out, None: never lent

    @property
    def in_use(self) -> bool:
        """Something still refers to the view handed out."""
        return self.lent is not None and self.lent() is not None


class BufferTaker:
    """Takes one subscription's messages into buffers of its own (module doc). Use from
    one thread, with the subscription's handle held (``with sub.handle``)."""

    def __init__(self, max_buffers: int = 16):
        if rcl_api.load() is None:
            raise RuntimeError("serialized takes through rcl are not available: "
                               f"{rcl_api.why_not()}")
        if max_buffers < 1:
            raise ValueError(f"max_buffers must be >= 1, got {max_buffers}")
        self.max_buffers = int(max_buffers)
        self._buffers: list[_Buffer] = []
        self._info = rcl_api.MessageInfo()
        #: messages that found every buffer lent (the caller took them another way)
        self.all_lent = 0

    def _free_buffer(self) -> _Buffer | None:
        for b in self._buffers:
            if not b.in_use:
                return b
        if len(self._buffers) >= self.max_buffers:
            return None
        api = rcl_api.load()
        msg = rcl_api.Serialized()
        alloc = api.allocator()
        if api.init(ctypes.byref(msg), 0, ctypes.byref(alloc)) != 0:
            raise rcl_api.rcl_error("rcutils_uint8_array_init failed")
        b = _Buffer(msg)
        self._buffers.append(b)
        return b

    def take(self, subscription_pointer: int):
        """The next serialized message of the subscription at ``subscription_pointer``
        (``sub.handle.pointer``) as a read-only uint8 array; None if there was none;
        ``NotImplemented`` if every buffer is lent (take it another way)."""
        buf = self._free_buffer()
        if buf is None:
            self.all_lent += 1
            return NotImplemented
        ret = rcl_api.load().take(subscription_pointer, ctypes.byref(buf.msg),
                                  ctypes.byref(self._info), None)
        if ret == rcl_api.TAKE_FAILED:
            return None
        if ret != 0:
            raise rcl_api.rcl_error(f"rcl_take_serialized_message failed ({ret})")
        n = buf.msg.buffer_length
        if n == 0:
            view = np.zeros(0, np.uint8)
        else:
            view = np.ctypeslib.as_array(buf.msg.buffer, shape=(n,))
        view.flags.writeable = False
        buf.lent = weakref.ref(view)
        return view

    def lent(self) -> int:
        """Buffers whose view is still referred to."""
        return sum(b.in_use for b in self._buffers)

    def close(self) -> None:
        """Free the buffers nobody refers to any more; those still lent are left to the
        process (freeing them would pull memory from under their views)."""
        keep = []
        for b in self._buffers:
            if b.in_use:
                keep.append(b)
            else:
                rcl_api.load().fini(ctypes.byref(b.msg))
        self._buffers = keep
