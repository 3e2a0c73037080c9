"""Child processes with and without the right to real-time scheduling, for the tests of
``lidar_quality_ros.threads.realtime_scheduling`` and the nodes' ``realtime_priority``."""
import subprocess
import sys

import pytest


# A process that starts a thread, asks for SCHED_FIFO, starts another thread and reports
# every thread's policy and priority (in a child: the test process stays as it is).
_RT_PROBE = """
import json, os, threading
from lidar_quality_ros.threads import realtime_scheduling
stop = threading.Event()
before = threading.Thread(target=stop.wait); before.start()
n, refused = realtime_scheduling(3)
after = threading.Thread(target=stop.wait); after.start()
tids = [int(t) for t in os.listdir("/proc/self/task")]
policies = sorted((os.sched_getscheduler(t), os.sched_getparam(t).sched_priority) for t in tids)
stop.set()
print(json.dumps({"n": n, "refused": refused, "threads": len(tids), "policies": policies}))
"""


def probe_realtime(prefix=(), preexec_fn=None) -> dict:
    import json

    out = subprocess.run([*prefix, sys.executable, "-c", _RT_PROBE], capture_output=True,
                         text=True, check=True, preexec_fn=preexec_fn).stdout
    return json.loads(out)


def without_realtime_rights():
    """(argv prefix, preexec_fn) that start a child with no right to real-time priority."""
    import os
    import resource
    import shutil

    def no_rtprio():
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    if os.geteuid() != 0:
        return (), no_rtprio
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root without setpriv: cannot take CAP_SYS_NICE away")
    return (setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice"), no_rtprio
