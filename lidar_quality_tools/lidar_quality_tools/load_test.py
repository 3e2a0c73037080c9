"""Live traffic through the quality nodes over DDS (issue 8): the one implementation
behind ``scripts/soak.py`` (10 minutes at 10 Hz) and ``bench/bench_e2e.py`` (latency,
drops, largest sustained rate).

:class:`LoadTest` starts the installed node executables (``<prefix>/lib/<pkg>/<node>``)
with their installed ``config/<node>.yaml`` as separate processes, each in its own
namespace (``/lmd``, ``/lms``, ``/mimo``), in a private ROS domain leased by
:class:`~lidar_quality_ros.testing.RosHarness` (DDS on loopback: the environment of
``scripts/env.sh``). It reads each node's input topics from the ROS graph, builds valid
frames for them (``lidar_quality_tools.fuzz.FrameTemplate``: synthetic 64-ring scans of
``n_points`` points with 50 detections, 500 proposals, head boxes and variances, class
probabilities), serializes them once, and pre-rolls until every node has answered.

:meth:`LoadTest.run` then publishes frames at a rate for a duration, every frame with a
new stamp written into the serialized bytes (no per-frame conversion by rclpy: an 8.6 MB
LMS cloud as a message object costs more than a 10 Hz period on two cores), and
measures per node:

* frames published, outputs received on the node's main output (matched by header
  stamp: outputs copy the input header), ``dropped`` = published frames without output;
* latency: from the start of the publication of the frame's inputs for that node (the
  ``publish`` call of its first input, taken when it is really made, not the scheduled
  tick) to the reception of its output by ``output_recorder``, a process of its own (raw
  subscription, no deserialization; not this one: a large publish here holds the GIL);
* resident memory (``VmRSS``) and CPU time of the node process, sampled every second,
  growth after a warm-up (:func:`memory_growth`);
* the node's own counters from ``/diagnostics`` (frames out, drops by reason,
  processing time percentiles);
* the publisher: publish call durations, ticks it ran late, the rate it achieved.

``recorder_priority`` > 0 runs the recorder's threads under SCHED_FIFO at that priority,
as the consumer of a node deployed with ``realtime_priority`` is (``output_recorder``
says why); what it got is ``recorder_scheduling`` in each run's report.

:func:`max_sustained_rate` steps a rate up until a step drops a frame.
"""
from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from lidar_quality_core.time_sync import HEADER_STAMP, stamp_of_bytes

from .output_recorder import parse_line

#: node -> (package, main output topic (relative) whose messages count as "received")
NODES = {"lmd": ("lmd_ros", "output/detections"),
         "lms": ("lms_ros", "output/segments"),
         "mimo": ("mimo_ros", "output/detections")}
_NS = 1_000_000_000


# ----------------------------------------------------------------------------- process
def rss_kb(pid: int) -> int | None:
    """Resident set size of a process [kB] (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def _stat_cpu(stat: str) -> tuple[str, float]:
    """``(comm, user + system CPU time [s])`` of a ``/proc/.../stat`` line."""
    fields = stat.rsplit(")", 1)[1].split()
    return (stat[stat.index("(") + 1:stat.rindex(")")],
            (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"))


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process [s]."""
    try:
        return _stat_cpu(Path(f"/proc/{pid}/stat").read_text())[1]
    except (FileNotFoundError, ProcessLookupError):
        return None


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """User + system CPU time [s] of a process's threads, summed by kind: the node
    executables name theirs (``lq_inputs``: input thread, ``lq_frames``: frame worker,
    ``lq_executor``: rclpy executor), Fast DDS's start with ``dds.``; the rest is
    ``other``. Threads that ended are not counted."""
    out: dict[str, float] = {}
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except (FileNotFoundError, ProcessLookupError):
        return out
    for task in tasks:
        try:
            comm, seconds = _stat_cpu((task / "stat").read_text())
        except (FileNotFoundError, ProcessLookupError):
            continue
        kind = (comm if comm.startswith("lq_") else "dds" if comm.startswith("dds.")
                else "other")
        out[kind] = out.get(kind, 0.0) + seconds
    return out


def _per_frame(snapshots: list, rate: float) -> dict[str, float]:
    """``{thread kind: CPU ms per frame}`` between the first and the last of
    ``[(t, thread_cpu_seconds), ...]`` at ``rate`` frames per second."""
    if len(snapshots) < 2 or rate <= 0 or snapshots[-1][0] <= snapshots[0][0]:
        return {}
    (t_a, a), (t_b, b) = snapshots[0], snapshots[-1]
    return {k: round((v - a.get(k, 0.0)) / (t_b - t_a) / rate * 1e3, 2)
            for k, v in sorted(b.items()) if v - a.get(k, 0.0) > 0}


def memory_growth(t: np.ndarray, kb: np.ndarray, warmup_s: float, window_s: float) -> dict:
    """RSS at the end of warm-up (median over ``window_s`` after ``warmup_s``), at the end
    (median over the last ``window_s``), growth between them in %, the growth over the
    second half of the time after warm-up (a leak grows in both halves; the allocator
    settling into its high-water mark mostly in the first), and the slope of a line
    fitted after warm-up [MB/min]."""
    t, kb = np.asarray(t, float), np.asarray(kb, float)
    after = t >= warmup_s
    if after.sum() < 2:
        return {"samples": int(len(t))}
    start = kb[after & (t < warmup_s + window_s)]
    end = kb[t > t[-1] - window_s]
    warm, last = float(np.median(start)), float(np.median(end))
    mid_t = (max(warmup_s, float(t[0])) + float(t[-1])) / 2
    mid = kb[np.abs(t - mid_t) <= window_s / 2]
    mid_kb = float(np.median(mid)) if len(mid) else warm
    slope = np.polyfit(t[after] / 60.0, kb[after] / 1024.0, 1)[0] if after.sum() > 2 else 0.0
    return {"samples": int(len(t)), "rss_warm_mb": round(warm / 1024, 1),
            "rss_end_mb": round(last / 1024, 1), "rss_max_mb": round(float(kb.max()) / 1024, 1),
            "growth_pct": round((last - warm) / warm * 100.0, 2),
            "growth_second_half_pct": round((last - mid_kb) / mid_kb * 100.0, 2),
            "slope_mb_per_min": round(float(slope), 3)}


def percentile(x, q) -> float | None:
    """The q-th percentile of x rounded to 0.01, None for no sample."""
    return round(float(np.percentile(x, q)), 2) if len(x) else None


# ----------------------------------------------------------------------------- outputs
class OutputLog:
    """Stamps of a node's outputs with their reception times, read from the raw CDR
    bytes (deserializing them would cost the receiver more than the measurement)."""

    def __init__(self):
        self.received: dict[int, float] = {}
        self.duplicates = 0
        self._lock = threading.Lock()

    def __call__(self, data: bytes) -> None:
        self.record(stamp_of_bytes(data), time.monotonic())

    def record(self, key: int, now: float) -> None:
        """An output of stamp ``key`` received at ``now`` (``time.monotonic()``)."""
        with self._lock:
            if key in self.received:
                self.duplicates += 1
            else:
                self.received[key] = now

    def snapshot(self) -> dict[int, float]:
        with self._lock:
            return dict(self.received)

    def count(self, stamps) -> int:
        with self._lock:
            return sum(1 for s in stamps if s in self.received)


class DiagnosticsLog:
    """The newest ``/diagnostics`` values of each node (status name ``<node>_node: ...``)."""

    def __init__(self):
        self.latest: dict[str, dict[str, str]] = {}
        self._lock = threading.Lock()

    def __call__(self, msg) -> None:
        for st in msg.status:
            name = st.name.split(":", 1)[0]
            with self._lock:
                self.latest[name] = {v.key: v.value for v in st.values}

    def values(self, node: str) -> dict[str, str]:
        with self._lock:
            return dict(self.latest.get(f"{node}_node", {}))


def node_command(name: str, *, params: dict | None = None, remaps: dict | None = None,
                 namespace: str | None = None) -> tuple[list[str], dict]:
    """``(argv, parameters)`` of a node executable as a user starts it: ``<name>_node``
    with its installed ``config/<name>_node.yaml``, in namespace ``/<name>`` (default),
    then ``-p`` overrides and ``-r`` remaps; ``parameters`` as the node will read them."""
    import yaml
    from ament_index_python.packages import get_package_prefix
    from lidar_quality_ros.params import config_file, config_parameters

    package = NODES[name][0]
    exe = Path(get_package_prefix(package)) / "lib" / package / f"{name}_node"
    cfg = config_file(package, f"{name}_node")
    values = config_parameters(package, f"{name}_node")
    argv = [str(exe), "--ros-args", "--params-file", str(cfg),
            "-r", f"__ns:={namespace or '/' + name}"]
    for k, v in (params or {}).items():
        argv += ["-p", f"{k}:={v}"]
        values[k] = yaml.safe_load(str(v))  # as the node reads it
    for old, new in (remaps or {}).items():
        argv += ["-r", f"{old}:={new}"]
    return argv, values


# ----------------------------------------------------------------------------- the test
@dataclass
class _Node:
    name: str
    proc: subprocess.Popen
    params: dict
    log: Path
    specs: list = field(default_factory=list)
    frames: list = field(default_factory=list)   # [[(publisher, bytearray)] per frame]
    output: OutputLog = field(default_factory=OutputLog)


class LoadTest:
    """The nodes ``names`` as processes, fed valid frames over DDS (see the module doc).

    Use as a context manager (``start()`` on entry, ``close()`` on exit)::

        with LoadTest(["lmd", "mimo"], out_dir) as lt:
            r = lt.run(duration=60, rate=10)
            r["nodes"]["lmd"]["latency_ms_p99"]
        lt.exit_codes   # {"lmd": 0, "mimo": 0}: clean exits on SIGINT
    """

    def __init__(self, names: Sequence[str], out_dir: Path, *, n_points: int = 120_000,
                 n_frames: int = 4, extra_params: dict | None = None, log_prefix: str = "",
                 start_timeout: float = 120.0, say: Callable[[str], None] | None = None,
                 recorder_priority: int = 0):
        unknown = set(names) - set(NODES)
        if unknown:
            raise ValueError(f"unknown node(s) {sorted(unknown)}; known: {', '.join(NODES)}")
        self.names = list(names)
        self.out_dir = Path(out_dir)
        self.n_points = int(n_points)
        self.n_frames = max(1, int(n_frames))
        self.extra_params = extra_params or {}
        self.recorder_priority = int(recorder_priority)
        #: what the recorder's threads run with, as it says (None until it has)
        self.recorder_scheduling: str | None = None
        self.log_prefix = log_prefix
        self.start_timeout = float(start_timeout)
        self.say = say or (lambda s: print(s, flush=True))
        self.ros = None
        self.nodes: dict[str, _Node] = {}
        self.exit_codes: dict[str, int | str] = {}
        self.preroll_frames = 0
        self._stamp_ns = 100 * _NS
        self._k = 0            # frame counter (which of the n_frames is next)
        self._all_sent: set[int] = set()

    # -- start ---------------------------------------------------------------------
    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.close()

    def start(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from lidar_quality_ros.qos import output_qos
        from lidar_quality_ros.testing import RosHarness

        self.out_dir.mkdir(parents=True, exist_ok=True)
        if not os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"):
            self.say("load test: warning: FASTRTPS_DEFAULT_PROFILES_FILE is not set (run "
                     "through scripts/with_env.sh): large clouds between processes get lost "
                     "without the shared-memory profile")
        self.ros = ros = RosHarness(num_threads=1)  # the publisher's GIL: cheap callbacks
        try:
            for name in self.names:
                argv, params = node_command(name, params=self.extra_params.get(name, {}))
                log = self.out_dir / f"{self.log_prefix}{name}_node.log"
                with open(log, "w") as fh:  # the child keeps its own descriptor
                    proc = ros.spawn(argv, stdout=fh, stderr=subprocess.STDOUT,
                                     extra_env={"PYTHONFAULTHANDLER": "1"})
                self.nodes[name] = _Node(name, proc, params, log)
            self.say(f"load test: ROS domain {ros.domain_id}; started "
                     + ", ".join(f"{n}_node (pid {x.proc.pid})" for n, x in self.nodes.items()))
            deadline = time.monotonic() + self.start_timeout
            for node in self.nodes.values():
                node.specs = self._wait_for_inputs(node, deadline)
            self._build_frames()
            types, outputs = {}, []
            for node in self.nodes.values():
                topic = f"/{node.name}/{NODES[node.name][1]}"
                while topic not in types:
                    self._check_alive(node)
                    if time.monotonic() > deadline:
                        raise RuntimeError(f"{node.name}_node does not publish {topic}")
                    time.sleep(0.2)
                    types = dict(ros.node.get_topic_names_and_types())
                outputs += [node.name, topic, types[topic][0]]
            self._start_recorder(outputs)
            self.diagnostics = DiagnosticsLog()
            self._diag_sub = ros.node.create_subscription(DiagnosticArray, "/diagnostics",
                                                          self.diagnostics, output_qos(50))
            for node in self.nodes.values():
                for pub, _ in node.frames[0]:
                    if not ros.wait_for_match(pub, timeout=30.0):
                        raise RuntimeError(f"{node.name}_node does not subscribe to {pub.topic_name}")
                if not self._matched[node.name].wait(timeout=30.0):
                    raise RuntimeError(f"no match with {node.name}_node's output (recorder "
                                       f"log: {self.out_dir / (self.log_prefix + 'recorder.log')})")
            self._preroll()
            gc.collect()
            gc.freeze()  # set-up objects out of the collector's way while publishing
        except BaseException:
            self.close()
            raise

    def _start_recorder(self, outputs: list[str]) -> None:
        """The nodes' outputs are received by ``output_recorder`` in a process of its own
        (its module doc says why), its lines read here into each node's ``OutputLog``."""
        log = open(self.out_dir / f"{self.log_prefix}recorder.log", "w")
        self._recorder = self.ros.spawn(
            [sys.executable, "-m", "lidar_quality_tools.output_recorder",
             *(["--realtime-priority", str(self.recorder_priority)]
               if self.recorder_priority > 0 else []), *outputs],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log)
        log.close()  # the child keeps its own descriptor
        self._matched = {n: threading.Event() for n in self.nodes}
        self._recorder_reader = threading.Thread(target=self._read_recorder, daemon=True)
        self._recorder_reader.start()

    def _read_recorder(self) -> None:
        for line in self._recorder.stdout:
            got = parse_line(line.decode(errors="replace"))
            if got is None:
                continue
            if got[0] == "r":
                self.nodes[got[1]].output.record(got[2], got[3])
            elif got[0] == "s":
                self.recorder_scheduling = got[1]
            else:
                self._matched[got[1]].set()

    def _check_alive(self, node: _Node) -> None:
        if node.proc.poll() is not None:
            raise RuntimeError(f"{node.name}_node exited with {node.proc.returncode} "
                               f"(log: {node.log})")

    def _wait_for_inputs(self, node: _Node, deadline: float) -> list:
        """InputSpecs of the node's subscriptions, read from the ROS graph once they stop
        changing (all of them, not the first only); detections before variances."""
        from lidar_quality_tools.fuzz import VARIANCES, input_spec
        from reference_perception.messages import probability_field
        name, params = node.name, node.params
        probs = (tuple(probability_field(c) for c in params["class_names"])
                 if name == "lms" else ())
        separate = bool(params.get("separate_probabilities"))
        last, stable_since = None, None
        while True:
            self._check_alive(node)
            try:
                subs = dict(self.ros.node.get_subscriber_names_and_types_by_node(
                    f"{name}_node", f"/{name}"))
            except Exception:  # noqa: BLE001 - the node is not in the graph yet
                subs = {}
            topics = {t: v[0] for t, v in subs.items() if t.startswith(f"/{name}/input/")}
            if topics and topics == last:
                if time.monotonic() - stable_since >= 0.5:
                    specs = [input_spec(t, ty, probs, separate) for t, ty in sorted(topics.items())]
                    return sorted(specs, key=lambda s: s.kind == VARIANCES)
            else:
                last, stable_since = topics, time.monotonic()
            if time.monotonic() > deadline:
                raise RuntimeError(f"{name}_node has no input subscriptions after "
                                   f"{self.start_timeout:.0f} s (log: {node.log})")
            time.sleep(0.1)

    def _build_frames(self) -> None:
        from lidar_quality_tools import fuzz
        self.say(f"load test: building {self.n_frames} frame(s) of {self.n_points} points "
                 f"per node")
        for node in self.nodes.values():
            box_classes = ({} if node.name == "lms"
                           else {"classes": tuple(node.params["class_names"])})
            templates = [fuzz.FrameTemplate(node.specs, n_points=self.n_points, n_objects=50,
                                            n_proposals=500, seed=k, **box_classes)
                         for k in range(self.n_frames)]
            pubs = {s.topic: self.ros.sensor_publisher(type(templates[0].messages[s.topic]),
                                                       s.topic)
                    for s in node.specs}
            # serialized once; each publication writes its stamp into the bytes
            node.frames = [[(pubs[s.topic], bytearray(t.serialized(s.topic)))
                            for s in node.specs] for t in templates]

    def frame_bytes(self) -> dict[str, int]:
        """Bytes of one frame per node (all its inputs)."""
        return {n: sum(len(b) for _, b in x.frames[0]) for n, x in self.nodes.items()}

    def _publish_tick(self, names, period_ns: int) -> tuple[int, dict[str, tuple[float, float]]]:
        """Publish the next frame of each node in ``names`` with the next stamp; returns
        the stamp and per node (publish start, publish end) times."""
        self._stamp_ns += period_ns
        stamp = self._stamp_ns
        sec, nsec = divmod(stamp, _NS)
        times = {}
        for n in names:
            frame = self.nodes[n].frames[self._k % self.n_frames]
            t0 = time.monotonic()
            for pub, buf in frame:
                HEADER_STAMP.pack_into(buf, 4, sec, nsec)
                pub.publish(bytes(buf))
            times[n] = (t0, time.monotonic())
        self._k += 1
        self._all_sent.add(stamp)
        return stamp, times

    def _preroll(self, rate: float = 10.0, timeout: float = 60.0) -> None:
        """Frames until every node has answered (its discovery of our writers)."""
        deadline = time.monotonic() + timeout
        k = 0
        while not all(x.output.received for x in self.nodes.values()):
            for x in self.nodes.values():
                self._check_alive(x)
            if time.monotonic() > deadline:
                silent = [n for n, x in self.nodes.items() if not x.output.received]
                raise RuntimeError(f"no output from {silent} within {timeout:.0f} s of pre-roll")
            self._publish_tick(self.names, int(_NS / rate))
            k += 1
            time.sleep(1.0 / rate)
        time.sleep(1.0)  # outputs of the pre-roll still in flight
        self.preroll_frames = k

    # -- one run -------------------------------------------------------------------
    def run(self, duration: float, rate: float, *, names: Sequence[str] | None = None,
            warmup: float = 0.0, memory_window: float | None = None,
            progress_every: float = 0.0, drain_timeout: float = 15.0,
            keep_series: bool = False) -> dict:
        """Publish ``round(duration * rate)`` frames at ``rate`` Hz to the nodes ``names``
        (default: all), wait for their outputs, and return the figures (module doc).

        ``warmup``: seconds after which the RSS reference is taken (memory growth from
        then to the end; medians over ``memory_window`` seconds, default
        ``max(2, min(30, duration / 10))``). The publisher keeps the rate: tick i is due at
        ``anchor + i / rate``; a tick more than one period late is published at once and
        counted (``late_ticks``), after a stall of more than max(0.5 s, 2 periods) the
        schedule skips ahead (``schedule_resets``: the achieved rate falls short). Each
        tick publishes the nodes' frames smallest first.
        """
        names = list(self.names if names is None else names)
        window = max(2.0, min(30.0, duration / 10)) if memory_window is None else memory_window
        n_total = max(1, int(round(duration * rate)))
        period = 1.0 / rate
        period_ns = int(round(_NS / rate))
        # smallest frames first: a small frame does not wait behind a large one's copy
        size = self.frame_bytes()
        names.sort(key=lambda n: size[n])
        pids = {n: self.nodes[n].proc.pid for n in names}
        samples: dict[str, list] = {n: [] for n in names}
        diag_before = {n: self.diagnostics.values(n) for n in names}
        dup_before = {n: self.nodes[n].output.duplicates for n in names}
        sent: dict[str, dict[int, float]] = {n: {} for n in names}
        pub_ms: dict[str, list[float]] = {n: [] for n in names}
        stop = threading.Event()

        by_thread: dict[str, list] = {n: [] for n in names}  # (t, first), (t, latest)

        def sample(t0: float) -> None:
            while True:
                now = time.monotonic() - t0
                for n, pid in pids.items():
                    kb = rss_kb(pid)
                    if kb is not None:
                        samples[n].append((now, kb, cpu_seconds(pid)))
                        by_thread[n][1:] = [(now, thread_cpu_seconds(pid))]
                if stop.wait(1.0):
                    return

        t0 = time.monotonic()
        sampler = threading.Thread(target=sample, args=(t0,), daemon=True)
        sampler.start()
        anchor = t0            # tick i is due at anchor + i * period
        late = resets = 0
        lag_ms: list[float] = []
        next_progress = progress_every
        for i in range(n_total):
            due = anchor + i * period
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
            elif now - due > max(0.5, 2 * period):
                resets += 1        # a long stall: skip ahead rather than burst
                anchor, due = now - i * period, now
            elif now - due > period:
                late += 1          # behind by a period: published at once (keeps the rate)
            stamp, times = self._publish_tick(names, period_ns)
            lag_ms.append((min(a for a, _ in times.values()) - due) * 1e3)
            for n, (a, b) in times.items():
                sent[n][stamp] = a
                pub_ms[n].append((b - a) * 1e3)
            if progress_every and time.monotonic() - t0 >= next_progress:
                next_progress += progress_every
                got = ", ".join(f"{n} {self.nodes[n].output.count(sent[n])}" for n in names)
                self.say(f"  {time.monotonic() - t0:.0f} s: sent {i + 1}, received {got}")
        t_end = time.monotonic()
        publish_s = t_end - t0
        # outputs in flight: until every node answered every frame, or went quiet
        last_change, counts = time.monotonic(), None
        while time.monotonic() - t_end < drain_timeout:
            now_counts = [self.nodes[n].output.count(sent[n]) for n in names]
            if all(c == len(sent[n]) for c, n in zip(now_counts, names)):
                break
            if now_counts != counts:
                counts, last_change = now_counts, time.monotonic()
            elif time.monotonic() - last_change > 2.0:
                break
            time.sleep(0.05)
        time.sleep(1.2)  # one more diagnostics period
        stop.set()
        sampler.join(timeout=5.0)

        report = {"duration_s": duration, "rate_hz": rate, "frames": n_total,
                  "publish_s": round(publish_s, 2),
                  "achieved_rate_hz": round((n_total - 1) / publish_s, 2) if publish_s > 0
                  and n_total > 1 else None,
                  "late_ticks": late, "schedule_resets": resets,
                  "tick_lag_ms_p99": percentile(lag_ms, 99),
                  "tick_lag_ms_max": round(max(lag_ms), 2) if lag_ms else None,
                  "warmup_s": warmup, "memory_window_s": window,
                  "recorder_scheduling": self.recorder_scheduling,
                  "nodes": {}}
        for n in names:
            node = self.nodes[n]
            received = node.output.snapshot()
            got = {s: received[s] for s in sent[n] if s in received}
            lat = np.array([(t - sent[n][s]) * 1e3 for s, t in got.items()])
            strangers = sum(1 for s, t in received.items()
                            if t >= t0 and s not in self._all_sent)
            values = self.diagnostics.values(n)
            before = diag_before[n]

            def delta(key, values=values, before=before):
                if key not in values:
                    return None
                return int(values[key]) - int(before.get(key, 0))
            arr = np.array(samples[n], dtype=float) if samples[n] else np.zeros((0, 3))
            span = arr[-1, 0] - arr[0, 0] if len(arr) > 1 else 0.0
            entry = {
                "published": len(sent[n]), "received": len(got),
                "dropped": len(sent[n]) - len(got),
                "unexpected_outputs": strangers,
                "duplicates": node.output.duplicates - dup_before[n],
                "latency_ms_p50": percentile(lat, 50), "latency_ms_p99": percentile(lat, 99),
                "latency_ms_max": round(float(lat.max()), 2) if len(lat) else None,
                "publish_ms_p50": percentile(pub_ms[n], 50),
                "publish_ms_p99": percentile(pub_ms[n], 99),
                "diag_frames_out": delta("frames_out"), "diag_dropped": delta("dropped"),
                "diag_dropped_reasons": {k: delta(k) for k in values
                                         if k.startswith("dropped.") and delta(k)},
                "processing_ms_p50": float(values["processing_ms_p50"])
                if "processing_ms_p50" in values else None,
                "processing_ms_p99": float(values["processing_ms_p99"])
                if "processing_ms_p99" in values else None,
                "memory": memory_growth(arr[:, 0], arr[:, 1], warmup, window) if len(arr) else {},
                "cpu_pct": (round(float((arr[-1, 2] - arr[0, 2]) / span * 100), 1)
                            if span > 0 else None),
                # process CPU time per frame at this rate (all threads: DDS, rclpy, ours)
                "cpu_ms_per_frame": (round(float((arr[-1, 2] - arr[0, 2]) / span / rate * 1e3),
                                           2) if span > 0 and rate > 0 else None),
                "alive": node.proc.poll() is None,
                # what the node runs with (its realtime_priority granted or refused)
                "scheduling": values.get("scheduling"),
                # the same by thread (lq_inputs, lq_frames, lq_executor, dds, other)
                "cpu_ms_per_frame_by_thread": _per_frame(by_thread[n], rate),
            }
            if keep_series:
                step = max(1, len(samples[n]) // 120)
                entry["rss_mb_series"] = [[round(t, 1), round(kb / 1024, 1)]
                                          for t, kb, _ in samples[n][::step]]
            report["nodes"][n] = entry
        return report

    # -- stop ----------------------------------------------------------------------
    def close(self, timeout: float = 30.0) -> dict[str, int | str]:
        """SIGINT to every node, their exit codes (``exit_codes``), the harness closed."""
        if self.ros is None:
            return self.exit_codes
        gc.unfreeze()
        for node in self.nodes.values():
            if node.proc.poll() is None:
                node.proc.send_signal(signal.SIGINT)
        for n, node in self.nodes.items():
            try:
                self.exit_codes[n] = node.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                node.proc.kill()
                node.proc.wait()
                self.exit_codes[n] = f"killed after {timeout:.0f} s"
        recorder = getattr(self, "_recorder", None)
        if recorder is not None and recorder.poll() is None:
            recorder.send_signal(signal.SIGINT)
            try:
                recorder.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                recorder.kill()
                recorder.wait()
            self._recorder_reader.join(timeout=5.0)
        ros, self.ros = self.ros, None
        ros.close()
        return self.exit_codes


# ----------------------------------------------------------------------------- rates
def step_ok(r: dict, node: str, min_rate_share: float = 0.97) -> tuple[bool, str]:
    """Whether a run sustained its rate for ``node``: no dropped frame, and the publisher
    achieved the rate (else the step measured the publisher, not the node)."""
    e = r["nodes"][node]
    if not e["alive"]:
        return False, "node died"
    if e["dropped"]:
        return False, f"{e['dropped']} dropped"
    achieved = r.get("achieved_rate_hz") or 0.0
    if achieved < min_rate_share * r["rate_hz"]:
        return False, f"publisher reached only {achieved:.1f} Hz"
    return True, "ok"


def max_sustained_rate(trial: Callable[[float], tuple[bool, str, dict]],
                       rates: Sequence[float]) -> tuple[float, list[dict]]:
    """Step through ``rates`` (ascending) calling ``trial(rate)`` -> (ok, why, figures)
    until a step fails; returns the last rate that passed (0 if none) and the steps."""
    best, steps = 0.0, []
    for rate in rates:
        ok, why, figures = trial(rate)
        steps.append({"rate_hz": rate, "ok": ok, "why": why, **figures})
        if not ok:
            break
        best = float(rate)
    return best, steps
