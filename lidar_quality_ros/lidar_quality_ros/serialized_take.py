"""Serialized messages taken into buffers the node keeps (rcl's C API through ctypes).

Why: rclpy's raw take (``take_message(..., raw=True)``) lets the rmw copy a message twice
(its history's payload into a CDR buffer, that into a serialized message allocated for the
call), then copies it a third time into a new ``bytes`` object and frees the second. For a
120k-point cloud (2-9 MB) the copies are most of an input thread's CPU: measured with
``perf`` in lmd_node at 10 Hz beside the other two nodes, 1.7 ms a frame of memmove for
a 2.8 MB frame. Here ``rcl_take_serialized_message`` writes into a serialized message that
stays ours between takes (grown once to the largest message seen), and the message is
handed over as a read-only numpy view of it: one copy fewer per message, and no
allocation.

A buffer is lent out with the view and reused only once nothing refers to the view any
more (a weak reference to it tells: views of the view keep it alive). At most
``max_buffers`` are lent at a time; a message that finds none free is taken by rclpy
(bytes, as before), so a node that holds many frames costs memory only up to that bound.

Linux and an rmw with serialized takes (every ROS 2 rmw) only; :func:`available` says
why not elsewhere, and the caller then keeps rclpy's take.
"""
from __future__ import annotations

import ctypes
import os
import weakref
from typing import NamedTuple

import numpy as np

__all__ = ["BufferTaker", "available"]

_TAKE_FAILED = 401  # RCL_RET_SUBSCRIPTION_TAKE_FAILED: nothing to take (not an error)


class _Allocator(ctypes.Structure):
    _fields_ = [("allocate", ctypes.c_void_p), ("deallocate", ctypes.c_void_p),
                ("reallocate", ctypes.c_void_p), ("zero_allocate", ctypes.c_void_p),
                ("state", ctypes.c_void_p)]


class _Serialized(ctypes.Structure):
    """rcl_serialized_message_t (rcutils_uint8_array_t)."""

    _fields_ = [("buffer", ctypes.POINTER(ctypes.c_uint8)), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", _Allocator)]


class _MessageInfo(ctypes.Structure):
    """rmw_message_info_t, with room to spare after it (never read past our fields)."""

    _fields_ = [("source_timestamp", ctypes.c_int64), ("received_timestamp", ctypes.c_int64),
                ("publication_sequence_number", ctypes.c_uint64),
                ("reception_sequence_number", ctypes.c_uint64),
                ("gid_implementation", ctypes.c_void_p), ("gid", ctypes.c_uint8 * 16),
                ("from_intra_process", ctypes.c_bool), ("_spare", ctypes.c_uint8 * 64)]


class _ErrorString(ctypes.Structure):
    _fields_ = [("str", ctypes.c_char * 1024)]


def _loaded(name: str) -> str | None:
    """Path of the shared library ``name`` (e.g. ``librcl.so``) this process has mapped."""
    try:
        with open("/proc/self/maps") as fh:
            for line in fh:
                path = line.rstrip("\n").split(maxsplit=5)[-1]
                if os.path.basename(path) == name:
                    return path
    except OSError:
        return None
    return None


class _Api(NamedTuple):
    """The C functions used here."""

    take: object      # rcl_take_serialized_message
    init: object      # rcutils_uint8_array_init
    fini: object      # rcutils_uint8_array_fini
    allocator: object  # rcutils_get_default_allocator
    error: object     # rcutils_get_error_string
    reset: object     # rcutils_reset_error


_api: _Api | None = None
_why_not = None


def _load():
    """The C functions used here, loaded once from the libraries rclpy has mapped."""
    global _api, _why_not
    if _api is not None or _why_not is not None:
        return _api
    try:
        import rclpy.impl.implementation_singleton  # noqa: F401 - maps librcl and its deps

        libs = {}
        for name in ("librcl.so", "librcutils.so"):
            path = _loaded(name)
            if path is None:
                raise OSError(f"{name} is not loaded in this process")
            libs[name] = ctypes.CDLL(path)
        rcl, rcutils = libs["librcl.so"], libs["librcutils.so"]
        take = rcl.rcl_take_serialized_message
        take.argtypes = [ctypes.c_void_p, ctypes.POINTER(_Serialized),
                         ctypes.POINTER(_MessageInfo), ctypes.c_void_p]
        take.restype = ctypes.c_int
        # rmw_serialized_message_init / _fini are macros over these
        init = rcutils.rcutils_uint8_array_init
        init.argtypes = [ctypes.POINTER(_Serialized), ctypes.c_size_t,
                         ctypes.POINTER(_Allocator)]
        init.restype = ctypes.c_int
        fini = rcutils.rcutils_uint8_array_fini
        fini.argtypes = [ctypes.POINTER(_Serialized)]
        fini.restype = ctypes.c_int
        allocator = rcutils.rcutils_get_default_allocator
        allocator.argtypes = []
        allocator.restype = _Allocator
        error = rcutils.rcutils_get_error_string
        error.argtypes = []
        error.restype = _ErrorString
        reset = rcutils.rcutils_reset_error
        reset.argtypes = []
        reset.restype = None
        _api = _Api(take, init, fini, allocator, error, reset)
    except (OSError, AttributeError, ImportError) as exc:
        _why_not = f"{type(exc).__name__}: {exc}"
    return _api


def _rcl_error(what: str) -> RuntimeError:
    """``what`` with rcutils' error string (which is then reset), as an exception to raise."""
    text = _api.error().str.decode(errors="replace")
    _api.reset()
    return RuntimeError(f"{what}: {text}")


def available() -> tuple[bool, str]:
    """``(True, "")`` if messages can be taken here, else ``(False, why not)``."""
    return (True, "") if _load() is not None else (False, _why_not or "unknown")


class _Buffer:
    __slots__ = ("msg", "lent")

    def __init__(self, msg: _Serialized):
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
        if _load() is None:
            raise RuntimeError(f"serialized takes through rcl are not available: {_why_not}")
        if max_buffers < 1:
            raise ValueError(f"max_buffers must be >= 1, got {max_buffers}")
        self.max_buffers = int(max_buffers)
        self._buffers: list[_Buffer] = []
        self._info = _MessageInfo()
        #: messages that found every buffer lent (the caller took them another way)
        self.all_lent = 0

    def _free_buffer(self) -> _Buffer | None:
        for b in self._buffers:
            if not b.in_use:
                return b
        if len(self._buffers) >= self.max_buffers:
            return None
        msg = _Serialized()
        alloc = _api.allocator()
        if _api.init(ctypes.byref(msg), 0, ctypes.byref(alloc)) != 0:
            raise _rcl_error("rcutils_uint8_array_init failed")
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
        ret = _api.take(subscription_pointer, ctypes.byref(buf.msg), ctypes.byref(self._info), None)
        if ret == _TAKE_FAILED:
            return None
        if ret != 0:
            raise _rcl_error(f"rcl_take_serialized_message failed ({ret})")
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
                _api.fini(ctypes.byref(b.msg))
        self._buffers = keep
