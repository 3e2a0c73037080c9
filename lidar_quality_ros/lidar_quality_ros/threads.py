"""Process and thread set-up of the node executables: OS-level thread names (so that
``top -H`` / ``ps -L`` tell a node's threads apart) and the allocator's trim policy."""
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


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: freed memory glibc keeps for reuse instead of handing it back to the kernel
KEEP_FREED_BYTES = 512 << 20
#: allocations below this come from the heap, not from a fresh mmap (glibc's maximum)
MMAP_THRESHOLD_BYTES = 32 << 20


def keep_freed_memory() -> bool:
    """Let glibc keep freed memory for the next frame (True if it was set).

    A frame allocates and frees the same large arrays (a 120k-point cloud's temporaries,
    0.5-8 MB each). By default glibc trims a thread's heap with ``madvise`` once more than
    128 kB is free at its top, and serves large blocks with ``mmap``; so every frame
    faulted its memory in again, page by page: in lmd_node at 10 Hz about a tenth of the
    frame thread's CPU was page faults and ``madvise`` in the kernel. The cost: the process
    keeps its peak footprint (what one frame needs) instead of shrinking between frames.
    Users may still override it with glibc's own ``MALLOC_TRIM_THRESHOLD_`` /
    ``MALLOC_MMAP_THRESHOLD_`` environment variables."""
    import os

    if _libc is None or not hasattr(_libc, "mallopt"):
        return False
    if "MALLOC_TRIM_THRESHOLD_" in os.environ or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False  # the user's choice
    ok = _libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    ok &= _libc.mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_BYTES)
    return bool(ok)
