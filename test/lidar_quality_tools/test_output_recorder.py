"""lidar_quality_tools.output_recorder: the load test's receiving process. Over real DDS
it says when a topic is matched, writes every message's stamp with its reception time on
the system's monotonic clock, and exits on SIGINT or when its stdin closes."""
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from lidar_quality_tools import fuzz
from lidar_quality_tools.fuzz import DETECTIONS, FrameTemplate, InputSpec
from lidar_quality_tools.output_recorder import parse_line
from lidar_quality_ros.qos import output_qos
from realtime_rights import probe_realtime, without_realtime_rights
from vision_msgs.msg import Detection3DArray


def test_parse_line():
    assert parse_line("r lmd 1500000000 12.25\n") == ("r", "lmd", 1500000000, 12.25)
    assert parse_line("m mimo\n") == ("m", "mimo")
    assert parse_line("s SCHED_FIFO 10\n") == ("s", "SCHED_FIFO 10")
    assert parse_line("s normal (refused: no)\n") == ("s", "normal (refused: no)")
    assert parse_line("garbage") is None and parse_line("") is None


def _lines(proc, into: list):
    for raw in proc.stdout:
        into.append(parse_line(raw.decode()))


def _matched_recorder(ros, *options, prefix=(), preexec_fn=None):
    """(recorder process, its parsed lines so far (growing), reader thread, deadline),
    the recorder on /out/detections started with ``options`` and matched."""
    proc = ros.spawn([*prefix, sys.executable, "-m", "lidar_quality_tools.output_recorder",
                      *options, "lmd", "/out/detections", "vision_msgs/msg/Detection3DArray"],
                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, preexec_fn=preexec_fn)
    got: list = []
    reader = threading.Thread(target=_lines, args=(proc, got), daemon=True)
    reader.start()
    deadline = time.monotonic() + 60.0
    while ("m", "lmd") not in got and time.monotonic() < deadline:
        assert proc.poll() is None
        time.sleep(0.05)
    assert ("m", "lmd") in got
    return proc, got, reader, deadline


def _thread_policies(pid: int) -> set:
    return {(os.sched_getscheduler(int(t)), os.sched_getparam(int(t)).sched_priority)
            for t in os.listdir(f"/proc/{pid}/task")}


@pytest.mark.parametrize("stop", ["sigint", "stdin"])
def test_recorder_process_reports_match_and_stamps(ros, stop):
    pub = ros.publisher(Detection3DArray, "out/detections", output_qos(10))
    proc, got, reader, deadline = _matched_recorder(ros)
    assert ("s", "normal") in got  # said before the match
    data = FrameTemplate([InputSpec("in", DETECTIONS)], n_points=100, n_objects=2,
                         n_proposals=2).serialized("in")
    t_sent = {}
    for sec in (7, 8, 9):
        t_sent[sec * 10**9] = time.monotonic()
        pub.publish(fuzz.restamp_bytes(data, sec * 10**9))
    while len([g for g in got if g and g[0] == "r"]) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    records = [g for g in got if g and g[0] == "r"]
    assert [(r[1], r[2]) for r in records] == [("lmd", s) for s in sorted(t_sent)]
    # the reception time is on this process's monotonic clock: after the publication
    for _, _, stamp, t in records:
        assert t_sent[stamp] <= t < t_sent[stamp] + 30.0
    if stop == "sigint":
        proc.send_signal(signal.SIGINT)
    else:
        proc.stdin.close()
    assert proc.wait(timeout=30.0) == 0
    reader.join(timeout=5.0)


@pytest.mark.parametrize("rights", ["granted", "refused"])
def test_recorder_realtime_priority_granted_or_said_refused(ros, rights):
    """``--realtime-priority 3``: every thread of the recorder SCHED_FIFO 3 once it has
    subscribed, and it says so; without the right it says why and stays normal, and
    records all the same."""
    prefix, preexec = ((), None) if rights == "granted" else without_realtime_rights()
    if rights == "granted" and not probe_realtime()["n"]:
        pytest.skip("this machine refuses SCHED_FIFO to the test process")
    pub = ros.publisher(Detection3DArray, "out/detections", output_qos(10))
    proc, got, reader, deadline = _matched_recorder(ros, "--realtime-priority", "3",
                                                    prefix=prefix, preexec_fn=preexec)
    said = [g[1] for g in got if g and g[0] == "s"]
    if rights == "granted":
        assert said == ["SCHED_FIFO 3"]
        assert _thread_policies(proc.pid) == {(os.SCHED_FIFO, 3)}
    else:
        assert len(said) == 1 and said[0].startswith("normal (refused: SCHED_FIFO priority 3")
        assert "CAP_SYS_NICE" in said[0]
        assert {p for p, _ in _thread_policies(proc.pid)} == {os.SCHED_OTHER}
    data = FrameTemplate([InputSpec("in", DETECTIONS)], n_points=100, n_objects=2,
                         n_proposals=2).serialized("in")
    pub.publish(fuzz.restamp_bytes(data, 5 * 10**9))
    while not any(g and g[0] == "r" for g in got) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert ("lmd", 5 * 10**9) in [(g[1], g[2]) for g in got if g and g[0] == "r"]
    proc.stdin.close()
    assert proc.wait(timeout=30.0) == 0
    reader.join(timeout=5.0)
