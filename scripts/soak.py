#!/usr/bin/env python3
"""Soak test (issue 8): lmd_node, lms_node and mimo_node at once, 10 Hz, 120k-point frames.

Starts the installed node executables (``ros2_ws/install/<pkg>/lib/<pkg>/<node>``) with
their installed ``config/<node>.yaml`` as separate processes, each in its own namespace,
in a private ROS domain. Their inputs are read from the ROS graph; valid frames for them
come from ``lidar_quality_ros.fuzz.FrameTemplate`` (synthetic 64-ring scans with
detections, proposals, head boxes and variances, class probabilities). After a pre-roll
that waits for every node's first output, frames are published at ``--rate`` for
``--duration`` seconds. Reported per node: frames published and received on its main
output (dropped = the difference, plus the node's own /diagnostics counters), latency
publication -> reception, resident memory (VmRSS from /proc/<pid>/status, sampled every
second) at the end of warm-up and at the end, its growth in %, and CPU use. The run
passes with no dropped frame, RSS growth below ``--max-growth`` % and a clean exit of
every node on SIGINT.

    bash scripts/with_env.sh python scripts/soak.py                   # 10 min
    bash scripts/with_env.sh python scripts/soak.py --duration 20 --nodes lmd
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
from lidar_quality_ros.fuzz import stamp_of_bytes

ROOT = Path(__file__).resolve().parents[1]
#: node -> (package, main output topic (relative) whose messages count as "received")
NODES = {"lmd": ("lmd_ros", "output/detections"),
         "lms": ("lms_ros", "output/segments"),
         "mimo": ("mimo_ros", "output/detections")}


def rss_kb(pid: int) -> int | None:
    """Resident set size of a process [kB] (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process [s]."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def memory_growth(t: np.ndarray, kb: np.ndarray, warmup_s: float, window_s: float) -> dict:
    """RSS at the end of warm-up (median over ``window_s`` after ``warmup_s``), at the end
    (median over the last ``window_s``), growth between them in %, and the slope of a
    line fitted after warm-up [MB/min]."""
    after = t >= warmup_s
    if after.sum() < 2:
        return {"samples": int(len(t))}
    t_end = t[-1]
    start = kb[after & (t < warmup_s + window_s)]
    end = kb[t > t_end - window_s]
    warm, last = float(np.median(start)), float(np.median(end))
    slope = np.polyfit(t[after] / 60.0, kb[after] / 1024.0, 1)[0] if after.sum() > 2 else 0.0
    return {"samples": int(len(t)), "rss_warm_mb": round(warm / 1024, 1),
            "rss_end_mb": round(last / 1024, 1), "rss_max_mb": round(float(kb.max()) / 1024, 1),
            "growth_pct": round((last - warm) / warm * 100.0, 2),
            "slope_mb_per_min": round(float(slope), 3)}


class Counter:
    """Output stamps of one node (read from the raw CDR bytes: deserializing them would
    load the driver), with reception times."""

    def __init__(self):
        self.received: dict[int, float] = {}
        self.duplicates = 0
        self._lock = threading.Lock()

    def __call__(self, data: bytes) -> None:
        now = time.monotonic()
        key = stamp_of_bytes(data)
        with self._lock:
            if key in self.received:
                self.duplicates += 1
            else:
                self.received[key] = now


def message_class(type_name: str):
    """Message class of a ROS type name ``pkg/msg/Name``."""
    import importlib
    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def node_inputs(ros, name: str, params: dict):
    """InputSpecs of a running node's subscriptions (from the ROS graph); detections
    before variances (a FrameTemplate builds variances from their boxes)."""
    from lidar_quality_ros.fuzz import VARIANCES, input_spec
    from reference_perception.messages import probability_field
    subs = dict(ros.node.get_subscriber_names_and_types_by_node(f"{name}_node", f"/{name}"))
    probs = (tuple(probability_field(c) for c in params["class_names"]) if name == "lms" else ())
    specs = [input_spec(t, subs[t][0], probs, bool(params.get("separate_probabilities")))
             for t in sorted(subs) if t.startswith(f"/{name}/input/")]
    return sorted(specs, key=lambda s: s.kind == VARIANCES)


def run(names: list[str], duration: float, rate: float, n_points: int, out: Path,
        n_frames: int = 4, warmup: float | None = None, extra_args: dict | None = None) -> dict:
    import yaml
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    from diagnostic_msgs.msg import DiagnosticArray
    from lidar_quality_ros import fuzz
    from lidar_quality_ros.qos import output_qos
    from lidar_quality_ros.testing import RosHarness

    out.parent.mkdir(parents=True, exist_ok=True)
    warmup = min(60.0, duration / 4) if warmup is None else warmup
    window = max(2.0, min(30.0, duration / 10))
    report: dict = {"duration_s": duration, "rate_hz": rate, "n_points": n_points,
                    "warmup_s": warmup, "window_s": window, "nodes": {},
                    "fastdds_profile": os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"),
                    "load_average_start": os.getloadavg()}
    if not report["fastdds_profile"]:
        print("soak: warning: FASTRTPS_DEFAULT_PROFILES_FILE is not set (run through "
              "scripts/with_env.sh): large clouds between processes get lost without the "
              "shared-memory profile", flush=True)
    with RosHarness() as ros:
        procs, params = {}, {}
        for name in names:
            package = NODES[name][0]
            exe = Path(get_package_prefix(package)) / "lib" / package / f"{name}_node"
            cfg = Path(get_package_share_directory(package)) / "config" / f"{name}_node.yaml"
            params[name] = yaml.safe_load(cfg.read_text())["/**"]["ros__parameters"]
            argv = [str(exe), "--ros-args", "--params-file", str(cfg), "-r", f"__ns:=/{name}"]
            for k, v in (extra_args or {}).get(name, {}).items():
                argv += ["-p", f"{k}:={v}"]
            log = open(out.parent / f"soak_{name}_node.log", "w")
            procs[name] = ros.spawn(argv, stdout=log, stderr=subprocess.STDOUT,
                                    extra_env={"PYTHONFAULTHANDLER": "1"})
            log.close()
        started = ", ".join(f"{n}_node (pid {p.pid})" for n, p in procs.items())
        print(f"soak: ROS domain {ros.domain_id}; started {started}", flush=True)
        # wait for each node's subscriptions to appear in the graph
        specs = {}
        deadline = time.monotonic() + 120.0
        for name in names:
            while True:
                if procs[name].poll() is not None:
                    raise RuntimeError(f"{name}_node exited with {procs[name].returncode} at start "
                                       f"(log: {out.parent / f'soak_{name}_node.log'})")
                try:
                    specs[name] = node_inputs(ros, name, params[name])
                except Exception:  # noqa: BLE001 - node not in the graph yet
                    specs[name] = []
                if specs[name]:
                    time.sleep(0.5)  # all subscriptions of the node, not the first only
                    specs[name] = node_inputs(ros, name, params[name])
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{name}_node has no input subscriptions after 120 s")
                time.sleep(0.2)
        print("soak: building frames", flush=True)
        templates = {}
        for n in names:
            box_classes = {} if n == "lms" else {"classes": tuple(params[n]["class_names"])}
            templates[n] = [fuzz.FrameTemplate(specs[n], n_points=n_points, n_objects=50,
                                               n_proposals=500, seed=k, **box_classes)
                            for k in range(n_frames)]
        pubs = {n: {s.topic: ros.sensor_publisher(type(templates[n][0].messages[s.topic]), s.topic)
                    for s in specs[n]} for n in names}
        # serialized once, restamped per publication (rclpy's conversion is far too slow)
        frames = {n: [[(s.topic, t.serialized(s.topic)) for s in specs[n]]
                      for t in templates[n]] for n in names}
        counters, subs = {}, []
        for n in names:
            topic = f"/{n}/{NODES[n][1]}"
            types = dict(ros.node.get_topic_names_and_types())
            deadline = time.monotonic() + 30.0
            while topic not in types and time.monotonic() < deadline:
                time.sleep(0.2)
                types = dict(ros.node.get_topic_names_and_types())
            counters[n] = Counter()
            subs.append(ros.node.create_subscription(message_class(types[topic][0]), topic,
                                                     counters[n], output_qos(50), raw=True))
        diag = ros.collector(DiagnosticArray, "/diagnostics")
        for n in names:
            for topic, p in pubs[n].items():
                if not ros.wait_for_match(p, timeout=30.0):
                    raise RuntimeError(f"{n}_node does not subscribe to {topic}")
        for s in subs:
            ros.wait_for_match(s, timeout=30.0)

        pids = {n: procs[n].pid for n in names}
        samples: dict[str, list] = {n: [] for n in names}
        stop = threading.Event()
        t0 = time.monotonic()

        def sample():
            while not stop.wait(1.0):
                now = time.monotonic() - t0
                for n, pid in pids.items():
                    kb = rss_kb(pid)
                    if kb is not None:
                        samples[n].append((now, kb, cpu_seconds(pid)))
        sampler = threading.Thread(target=sample, daemon=True)

        def publish(n: str, k: int, stamp_ns: int) -> None:
            for topic, data in frames[n][k % n_frames]:
                pubs[n][topic].publish(fuzz.restamp_bytes(data, stamp_ns))

        # pre-roll: until every node has answered (discovery of our writers by the nodes)
        stamp = 100 * 1_000_000_000
        period_ns = int(round(1e9 / rate))
        deadline = time.monotonic() + 60.0
        k = 0
        while not all(c.received for c in counters.values()):
            if time.monotonic() > deadline:
                silent = [n for n, c in counters.items() if not c.received]
                raise RuntimeError(f"no output from {silent} within 60 s of pre-roll")
            for n in names:
                publish(n, k, stamp)
            stamp += period_ns
            k += 1
            time.sleep(1.0 / rate)
        time.sleep(1.0)
        for c in counters.values():
            c.received.clear()
        print(f"soak: pre-roll {k} frames; running {duration:.0f} s at {rate:g} Hz, "
              f"{n_points} points per cloud", flush=True)

        # the soak
        sent: dict[int, float] = {}
        first = stamp
        sampler.start()
        t0 = time.monotonic()
        t_next = t0
        late = 0
        i = 0
        while True:
            now = time.monotonic()
            if now - t0 >= duration:
                break
            if t_next > now:
                time.sleep(t_next - now)
            elif now - t_next > 1.0 / rate:
                late += 1  # the publisher itself fell behind by a period
            sent[stamp] = time.monotonic()
            for n in names:
                publish(n, i, stamp)
            stamp += period_ns
            i += 1
            t_next += 1.0 / rate
            if i % int(rate * 60) == 0:
                got = ", ".join(f"{n} {sum(1 for s in c.received if s >= first)}"
                                for n, c in counters.items())
                print(f"  {i / rate:.0f} s: sent {i}, received {got}", flush=True)
        time.sleep(3.0)  # outputs in flight, one more diagnostics period
        stop.set()
        sampler.join(timeout=5.0)

        for n in names:
            c = counters[n]
            got = {s: t for s, t in c.received.items() if s in sent}
            lat = np.array([(t - sent[s]) * 1e3 for s, t in got.items()])
            status = [st for m in diag.messages for st in m.status
                      if st.name.startswith(f"{n}_node")]
            values = {v.key: v.value for v in status[-1].values} if status else {}
            arr = np.array(samples[n], dtype=float) if samples[n] else np.zeros((0, 3))
            span = arr[-1, 0] - arr[0, 0] if len(arr) > 1 else 0.0
            proc_ms = {k: float(values[k]) if k in values else None
                       for k in ("processing_ms_p50", "processing_ms_p99")}
            step = max(1, len(samples[n]) // 120)
            entry = {
                "published": len(sent), "received": len(got),
                "dropped": len(sent) - len(got),
                "unexpected_outputs": len(c.received) - len(got), "duplicates": c.duplicates,
                "diag_frames_out": int(values.get("frames_out", -1)),
                "diag_dropped": int(values.get("dropped", -1)),
                "diag_dropped_reasons": {k: v for k, v in values.items()
                                         if k.startswith("dropped.")},
                "latency_ms_p50": round(float(np.percentile(lat, 50)), 1) if len(lat) else None,
                "latency_ms_p99": round(float(np.percentile(lat, 99)), 1) if len(lat) else None,
                **proc_ms,
                "memory": memory_growth(arr[:, 0], arr[:, 1], warmup, window) if len(arr) else {},
                "cpu_pct": (round(float((arr[-1, 2] - arr[0, 2]) / span * 100), 1)
                            if span > 0 else None),
                "rss_mb_series": [[round(t, 1), round(kb / 1024, 1)]
                                  for t, kb, _ in samples[n][::step]],
            }
            report["nodes"][n] = entry
        report["publisher_late_ticks"] = late
        report["load_average_end"] = os.getloadavg()
        for n in names:
            procs[n].send_signal(signal.SIGINT)
        for n in names:
            try:
                report["nodes"][n]["exit_code"] = procs[n].wait(timeout=30)
            except subprocess.TimeoutExpired:
                procs[n].kill()
                report["nodes"][n]["exit_code"] = "killed after 30 s"
    return report


def print_report(r: dict, max_growth: float) -> None:
    nan = float("nan")
    print(f"\nsoak: {r['duration_s']:.0f} s at {r['rate_hz']:g} Hz, {r['n_points']} points "
          f"per cloud; RSS growth from the end of a {r['warmup_s']:.0f} s warm-up to the end "
          f"(medians over {r['window_s']:.0f} s); load average "
          f"{r['load_average_start'][0]:.1f} -> {r['load_average_end'][0]:.1f}")
    print(f"{'node':5s} {'sent':>6s} {'recv':>6s} {'drop':>5s} {'lat p50':>8s} {'lat p99':>8s} "
          f"{'RSS warm':>9s} {'RSS end':>8s} {'growth':>7s} {'MB/min':>7s} {'CPU %':>6s} "
          f"{'exit':>5s}")
    for n, e in r["nodes"].items():
        m = e["memory"]
        print(f"{n:5s} {e['published']:6d} {e['received']:6d} {e['dropped']:5d} "
              f"{e['latency_ms_p50'] or nan:8.1f} {e['latency_ms_p99'] or nan:8.1f} "
              f"{m.get('rss_warm_mb', nan):9.1f} {m.get('rss_end_mb', nan):8.1f} "
              f"{m.get('growth_pct', nan):6.2f}% {m.get('slope_mb_per_min', nan):7.3f} "
              f"{e['cpu_pct'] or nan:6.1f} {e['exit_code']!s:>5s}")
    ok = passed(r, max_growth)
    print(f"-> {'PASS' if ok else 'FAIL'} (no drop, RSS growth < {max_growth:g} %, clean exit)")


def passed(r: dict, max_growth: float) -> bool:
    return all(e["dropped"] == 0 and e["exit_code"] == 0
               and e["memory"].get("growth_pct", float("inf")) < max_growth
               for e in r["nodes"].values())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of 10 Hz input")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--points", type=int, default=120_000)
    ap.add_argument("--nodes", default="lmd,lms,mimo")
    ap.add_argument("--frames", type=int, default=4, help="distinct frames, sent in turn")
    ap.add_argument("--warmup", type=float, default=None,
                    help="seconds before the RSS reference (default: min(60, duration / 4))")
    ap.add_argument("--max-growth", type=float, default=5.0, help="RSS growth limit [%%]")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="extra node parameter, e.g. lmd.classifier_path=/x.joblib")
    ap.add_argument("--out", default=str(ROOT / "out" / "soak" / "report.json"))
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.nodes.split(",") if n.strip()]
    if set(names) - set(NODES):
        ap.error(f"unknown node(s); known: {', '.join(NODES)}")
    extra: dict[str, dict] = {}
    for p in args.param:
        key, _, value = p.partition("=")
        node, _, pname = key.partition(".")
        extra.setdefault(node, {})[pname] = value
    out = Path(args.out)
    r = run(names, args.duration, args.rate, args.points, out, n_frames=args.frames,
            warmup=args.warmup, extra_args=extra)
    r["passed"] = passed(r, args.max_growth)
    r["max_growth_pct"] = args.max_growth
    out.write_text(json.dumps(r, indent=1) + "\n")
    print_report(r, args.max_growth)
    print(f"wrote {out}")
    return 0 if r["passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
