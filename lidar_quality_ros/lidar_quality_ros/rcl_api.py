"""The few rcl / rcutils C functions the nodes call through ctypes, for serialized messages
that rclpy would copy once more: :mod:`~lidar_quality_ros.serialized_take` (inputs taken
into buffers of our own) and :mod:`~lidar_quality_ros.serialized_publish` (outputs
published from our own buffers).

Loaded once from the libraries rclpy has mapped into the process (the same rcl, the same
rmw), so they act on rclpy's handles (``handle.pointer``). Linux only (``/proc/self/maps``);
:func:`load` returns None elsewhere or when a library or a symbol is missing, and
:func:`why_not` says why; callers then keep rclpy's own path.
"""
from __future__ import annotations

import ctypes
import os
from typing import NamedTuple

__all__ = ["Serialized", "MessageInfo", "load", "why_not", "rcl_error", "TAKE_FAILED"]

TAKE_FAILED = 401  # RCL_RET_SUBSCRIPTION_TAKE_FAILED: nothing to take (not an error)


class Allocator(ctypes.Structure):
    """rcutils_allocator_t."""

    _fields_ = [("allocate", ctypes.c_void_p), ("deallocate", ctypes.c_void_p),
                ("reallocate", ctypes.c_void_p), ("zero_allocate", ctypes.c_void_p),
                ("state", ctypes.c_void_p)]


class Serialized(ctypes.Structure):
    """rcl_serialized_message_t (rcutils_uint8_array_t)."""

    _fields_ = [("buffer", ctypes.POINTER(ctypes.c_uint8)), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", Allocator)]


class MessageInfo(ctypes.Structure):
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


class Api(NamedTuple):
    """The C functions used."""

    take: object      # rcl_take_serialized_message
    publish: object   # rcl_publish_serialized_message
    init: object      # rcutils_uint8_array_init
    fini: object      # rcutils_uint8_array_fini
    allocator: object  # rcutils_get_default_allocator
    error: object     # rcutils_get_error_string
    reset: object     # rcutils_reset_error


_api: Api | None = None
_why_not = None


def load() -> Api | None:
    """The C functions, loaded once from the libraries rclpy has mapped; None if they
    cannot be (:func:`why_not`)."""
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
        take.argtypes = [ctypes.c_void_p, ctypes.POINTER(Serialized),
                         ctypes.POINTER(MessageInfo), ctypes.c_void_p]
        take.restype = ctypes.c_int
        publish = rcl.rcl_publish_serialized_message
        publish.argtypes = [ctypes.c_void_p, ctypes.POINTER(Serialized), ctypes.c_void_p]
        publish.restype = ctypes.c_int
        # rmw_serialized_message_init / _fini are macros over these
        init = rcutils.rcutils_uint8_array_init
        init.argtypes = [ctypes.POINTER(Serialized), ctypes.c_size_t,
                         ctypes.POINTER(Allocator)]
        init.restype = ctypes.c_int
        fini = rcutils.rcutils_uint8_array_fini
        fini.argtypes = [ctypes.POINTER(Serialized)]
        fini.restype = ctypes.c_int
        allocator = rcutils.rcutils_get_default_allocator
        allocator.argtypes = []
        allocator.restype = Allocator
        error = rcutils.rcutils_get_error_string
        error.argtypes = []
        error.restype = _ErrorString
        reset = rcutils.rcutils_reset_error
        reset.argtypes = []
        reset.restype = None
        _api = Api(take, publish, init, fini, allocator, error, reset)
    except (OSError, AttributeError, ImportError) as exc:
        _why_not = f"{type(exc).__name__}: {exc}"
    return _api


def why_not() -> str:
    """Why :func:`load` returned None ("" if it did not)."""
    return "" if _api is not None else (_why_not or "not loaded yet")


def rcl_error(what: str) -> RuntimeError:
    """``what`` with rcutils' error string (which is then reset), as an exception to raise."""
    text = _api.error().str.decode(errors="replace")
    _api.reset()
    return RuntimeError(f"{what}: {text}")
