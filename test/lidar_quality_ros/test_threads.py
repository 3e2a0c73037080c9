"""Thread names in the kernel and the allocator policy of the node executables."""
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from lidar_quality_ros.threads import name_os_thread
from realtime_rights import probe_realtime, without_realtime_rights


def test_a_thread_is_named_in_the_kernel():
    seen = []

    def run():
        name_os_thread("lq_test_thread_with_a_long_name")
        seen.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip())

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert seen == ["lq_test_thread_"]  # the kernel keeps 15 bytes


_PROBE = "from lidar_quality_ros.threads import keep_freed_memory; print(keep_freed_memory())"


def test_freed_memory_is_kept_unless_the_user_set_glibc_s_own_variables():
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == "True"
    out = subprocess.run([sys.executable, "-c", _PROBE],
                         env={**env, "MALLOC_TRIM_THRESHOLD_": "131072"}, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == "False"



# On one thread: 48 MB of frame-sized arrays, with or without touch_memory(64) before; the
# memory [MB] the arrays added to the process (RSS) and what the warm-up kept.
_REUSE_PROBE = """
import sys, threading
import numpy as np
from lidar_quality_ros.threads import keep_freed_memory, touch_memory
keep_freed_memory()
def rss():
    return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) >> 10
def run():
    r0 = rss()
    if sys.argv[1] == "warm":
        assert touch_memory(64) > 0
    r1 = rss()
    arrays = [np.ones(2 << 20) for _ in range(3)]  # 3 x 16 MB, written
    print(rss() - r1, r1 - r0)
t = threading.Thread(target=run)
t.start()
t.join()
"""


def test_touched_memory_stays_with_the_thread_for_its_next_arrays():
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}

    def probe(mode):
        out = subprocess.run([sys.executable, "-c", _REUSE_PROBE, mode], env=env, capture_output=True,
                             text=True, check=True).stdout.split()
        return int(out[0]), int(out[1])

    cold_added, _ = probe("cold")
    warm_added, kept_mb = probe("warm")
    assert cold_added >= 40  # fresh pages, each faulted in by the arrays
    assert warm_added <= 8  # the pages the warm-up wrote, reused
    assert kept_mb >= 48  # freed, yet kept by the thread's heap


def test_realtime_scheduling_covers_every_thread_and_those_started_later():
    import os

    r = probe_realtime()
    if r["refused"]:
        pytest.skip(f"this machine refuses SCHED_FIFO to the test: {r['refused']}")
    # the main thread, `before` and `after`: all FIFO 3 (`after` by inheritance)
    assert r["threads"] == 3 and r["n"] == 2
    assert r["policies"] == [[os.SCHED_FIFO, 3]] * 3


def test_realtime_scheduling_refused_says_why_and_changes_nothing():
    import os

    r = probe_realtime(*without_realtime_rights())
    assert r["n"] == 0
    assert "SCHED_FIFO priority 3 refused" in r["refused"] and "ulimit -r" in r["refused"]
    assert r["policies"] == [[os.SCHED_OTHER, 0]] * 3
