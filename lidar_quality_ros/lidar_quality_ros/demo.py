"""``make demo``: the suite end to end on synthetic frames, over DDS, between processes.

Starts the three node executables (``lmd_node``, ``lms_node``, ``mimo_node``) with
their parameter files, publishes synthetic 120k-point frames at 10 Hz (cloud,
detections, two detector heads), collects the outputs and ``/diagnostics``, and prints
and writes a summary: frames in / out / dropped and latency per node.
At this stage the nodes are shells (pass-through; see their docstrings): the summary
shows the plumbing, not yet quality figures.
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_prefix
from diagnostic_msgs.msg import DiagnosticArray
from lidar_quality_core.boxes import arrays_to_detections
from lidar_quality_core.pointcloud import create_xyz_cloud
from lidar_quality_core.synthetic import CLASS_NAMES, synthetic_frame
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from vision_msgs.msg import Detection3DArray

from .testing import RosHarness

NODES = {  # node -> (package, input topics, output topic, output type)
    "lmd": ("lmd_ros", ["input/points", "input/detections", "input/proposals"], "output/detections",
            Detection3DArray),
    "lms": ("lms_ros", ["input/points"], "output/points", PointCloud2),
    "mimo": ("mimo_ros", ["input/head_0", "input/head_1"], None, None),
}


def _start_node(ros: RosHarness, name: str, log_dir: Path) -> subprocess.Popen:
    package = NODES[name][0]
    prefix = Path(get_package_prefix(package))
    exe = prefix / "lib" / package / f"{name}_node"
    params = prefix / "share" / package / "config" / f"{name}_node.yaml"
    argv = [str(exe), "--ros-args", "--params-file", str(params), "-r", f"__ns:=/{name}"]
    with open(log_dir / f"{name}_node.log", "w") as log:  # the child keeps its own copy
        return ros.spawn(argv, stdout=log, stderr=subprocess.STDOUT,
                         extra_env={"PYTHONFAULTHANDLER": "1"})  # a crash leaves its stack in the log


def run(out_dir: Path, frames: int = 50, rate_hz: float = 10.0, n_points: int = 120_000) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    frame_data = [synthetic_frame(n_points=n_points, seed=s) for s in range(min(frames, 10))]
    # lmd_node (threshold mode) also takes the pre-NMS proposals; built once per frame
    proposals = [arrays_to_detections(Header(), f.proposals, [CLASS_NAMES[c] for c in f.prop_classes],
                                      f.prop_scores) for f in frame_data]
    with RosHarness() as ros:
        print(f"demo: ROS domain {ros.domain_id}, loopback only; starting lmd_node, lms_node, mimo_node")
        procs = {n: _start_node(ros, n, out_dir) for n in NODES}
        pubs = {f"/{n}/{t}": ros.sensor_publisher(PointCloud2 if t.endswith("points") else Detection3DArray,
                                                   f"/{n}/{t}")
                for n, spec in NODES.items() for t in spec[1]}
        outs = {n: ros.collector(spec[3], f"/{n}/{spec[2]}") for n, spec in NODES.items() if spec[2]}
        diag = ros.collector(DiagnosticArray, "/diagnostics")
        # Matched on both ends before the first frame: best-effort samples sent earlier are lost.
        for topic, pub in pubs.items():
            if not ros.wait_for_match(pub, timeout=30.0):
                raise RuntimeError(f"no node subscribed to {topic} within 30 s")
        for n, col in outs.items():
            if not ros.wait_for_match(col.subscription, timeout=30.0):
                raise RuntimeError(f"{n}_node does not publish {NODES[n][2]}")
        time.sleep(0.5)
        sent_at: dict[int, float] = {}
        period = 1.0 / rate_hz
        t_next = time.monotonic()
        for i in range(frames):
            f = frame_data[i % len(frame_data)]
            h = Header(frame_id="lidar_top")
            h.stamp.sec, h.stamp.nanosec = 1000 + i // 10, (i % 10) * 100_000_000
            cloud = create_xyz_cloud(h, f.points, f.intensity)
            labels = [CLASS_NAMES[c] for c in f.det_classes]
            dets = arrays_to_detections(h, f.detections, labels, f.det_scores,
                                        ids=[f"{i}-{k}" for k in range(len(labels))])
            rng = np.random.default_rng(i)
            heads = [arrays_to_detections(h, f.detections + rng.normal(0, 0.1, f.detections.shape) * [1, 1, 0, 0, 0, 0, 0],
                                          labels, f.det_scores) for _ in range(2)]
            time.sleep(max(0.0, t_next - time.monotonic()))
            t_next += period
            sent_at[i] = time.monotonic()
            props = proposals[i % len(frame_data)]
            props.header = h
            pubs["/lmd/input/detections"].publish(dets)
            pubs["/lmd/input/proposals"].publish(props)
            pubs["/lmd/input/points"].publish(cloud)
            pubs["/lms/input/points"].publish(cloud)
            pubs["/mimo/input/head_0"].publish(heads[0])
            pubs["/mimo/input/head_1"].publish(heads[1])
        for col in outs.values():
            col.wait_for(frames, timeout=5.0)
        time.sleep(1.5)  # one more diagnostics period
        summary = {}
        for n in NODES:
            status = [s for m in diag.messages for s in m.status if s.name.startswith(f"{n}_node")]
            values = {v.key: v.value for v in status[-1].values} if status else {}
            entry = {"frames_in": frames,
                     "frames_out": int(values.get("frames_out", 0)),
                     "dropped": int(values.get("dropped", 0))}
            if n in outs:
                col = outs[n]
                lat = [(t - sent_at[_frame_index(m)]) * 1e3
                       for m, t in zip(col.messages, col.receive_times)]
                entry["latency_ms"] = [round(x, 1) for x in lat]
                entry.update(latency_ms_p50=round(float(np.percentile(lat, 50)), 2) if lat else None,
                             latency_ms_p99=round(float(np.percentile(lat, 99)), 2) if lat else None)
            summary[n] = entry
        for n, proc in procs.items():
            proc.send_signal(signal.SIGINT)
        for n, proc in procs.items():
            summary[n]["exit_code"] = proc.wait(timeout=15)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"\n{'node':6s} {'in':>5s} {'out':>5s} {'dropped':>8s} {'lat p50 ms':>11s} {'lat p99 ms':>11s}")
    for n, e in summary.items():
        print(f"{n:6s} {e['frames_in']:5d} {e['frames_out']:5d} {e['dropped']:8d} "
              f"{str(e.get('latency_ms_p50', '-')):>11s} {str(e.get('latency_ms_p99', '-')):>11s}")
    print(f"\nwrote {out_dir / 'summary.json'} (node logs beside it)")
    return summary


def _frame_index(msg) -> int:
    s = msg.header.stamp
    return (s.sec - 1000) * 10 + s.nanosec // 100_000_000


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/demo")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--rate", type=float, default=10.0)
    args = ap.parse_args(argv)
    summary = run(Path(args.out), frames=args.frames, rate_hz=args.rate)
    # Dropped frames are reported, not fatal (a loaded machine may drop one); a node that
    # crashed or produced nothing fails the demo.
    ok = all(e["frames_out"] > 0 and e["exit_code"] == 0 for e in summary.values())
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
