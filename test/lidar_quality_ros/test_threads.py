"""Thread names in the kernel and the allocator policy of the node executables."""
import subprocess
import sys
import threading
from pathlib import Path

from lidar_quality_ros.threads import name_os_thread


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

