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


#: size of the blocks touch_memory allocates: below MMAP_THRESHOLD_BYTES, so that they come
#: from (and go back to) the thread's heap, as a frame's arrays do
_TOUCH_BLOCK_BYTES = 4 << 20


def touch_memory(megabytes: float) -> float:
    """Allocate ``megabytes`` on the calling thread, write every page, free it; returns
    the seconds it took.

    Why: on a virtual machine the first write to a page the guest has not used lately
    costs far more than a write to a page it has (measured on the 2-core VM: 256 MB in
    0.85 s at node start-up, against 15-20 ms for memory freed moments before). A node's
    first frames allocate their working set (about 100 MB in lms_node) and paid that: the
    first LMS frame of a fresh clone's demo took 260-320 ms instead of 60-80 and the
    frames behind it overflowed the queue. Done at start-up on the frame and input
    threads, with ``keep_freed_memory``, the pages stay with the thread's heap and the
    frames reuse them."""
    import time

    import numpy as np

    t0 = time.perf_counter()
    n = int(megabytes * (1 << 20)) // _TOUCH_BLOCK_BYTES
    blocks = []
    for _ in range(n):
        b = np.empty(_TOUCH_BLOCK_BYTES, dtype=np.uint8)
        b.fill(1)  # np.zeros may map the kernel's zero page instead of writing
        blocks.append(b)
    del blocks
    return time.perf_counter() - t0


def realtime_scheduling(priority: int) -> tuple[int, str | None]:
    """Put every thread of this process under ``SCHED_FIFO`` at ``priority`` (1-99);
    threads started later inherit it. Returns (threads set, None) or (0, why it was refused).

    Why a node wants it: on two cores the three nodes, the cloud publishers and the
    subscribers all wake within a few milliseconds of each frame, and a thread woken into
    that waits for a core (MIMO's input thread: 5-9 ms for one frame in six, measured).
    A FIFO thread takes a core at once; the kernel's real-time throttling (by default 95 %
    of each second) keeps a runaway one from freezing the machine. Needs CAP_SYS_NICE or
    an RLIMIT_RTPRIO of at least ``priority``; refused, nothing is changed."""
    import os

    if not hasattr(os, "sched_setscheduler") or not os.path.isdir("/proc/self/task"):
        return 0, "real-time scheduling is not available on this system"
    param = os.sched_param(priority)
    done: list[tuple[int, int, int]] = []
    for name in os.listdir("/proc/self/task"):
        tid = int(name)
        try:
            before = os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
        except ProcessLookupError:
            continue  # the thread ended meanwhile
        except OSError as exc:
            for t, policy, prio in done:  # all or nothing
                try:
                    os.sched_setscheduler(t, policy, os.sched_param(prio))
                except OSError:
                    pass
            return 0, (f"SCHED_FIFO priority {priority} refused ({exc.strerror}): it needs "
                       f"CAP_SYS_NICE or a real-time priority limit of at least {priority} "
                       "(`ulimit -r`, rtprio in /etc/security/limits.conf, LimitRTPRIO= in "
                       "a systemd unit); and, in a container, a real-time CPU budget")
        done.append((tid, *before))
    return len(done), None
