"""OS-level thread names, so that ``top -H`` / ``ps -L`` tell a node's threads apart."""
from __future__ import annotations

import ctypes
import ctypes.util

_PR_SET_NAME = 15
try:
    _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
except OSError:  # not Linux: names are a convenience, never a requirement
    _libc = None


def name_os_thread(name: str) -> None:
    """Name the calling thread in the kernel (at most 15 bytes are kept)."""
    if _libc is not None and hasattr(_libc, "prctl"):
        _libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)
