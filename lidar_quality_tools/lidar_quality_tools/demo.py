"""``make demo``: the three nodes on a replayed perception bag, evaluated against the ground truth.

1. The input: a perception bag (``make demo`` generates the simulated ``demo`` split,
   100 frames at 10 Hz, into ``data/perception/demo`` once, then reuses it).
2. ``lmd_node``, ``lms_node`` and ``mimo_node`` start as processes, as a user starts them:
   installed executable, ``config/<node>.yaml``, namespace ``/lmd`` ``/lms`` ``/mimo``,
   ``use_sim_time:=true``, inputs remapped onto the bag's topics (LMS reads the points
   and the probabilities on two topics, so the ring field gives the image rows, as the
   shipped models were trained).
3. ``bag_player`` (a process) replays the bag in real time with ``/clock`` (a stall of
   the player shifts the rest of the bag instead of bursting it: ``MAX_LATENESS_S``); a recorder in
   this process writes the nodes' outputs (raw CDR, log time = header stamp) to
   ``<out>/outputs`` and notes when every input and output arrived.
4. :mod:`.evaluation` scores the recorded outputs against the ground truth; the report
   (``report.md``, ``summary.json``, PNG plots) goes to ``<out>``.
5. A summary is printed; its first lines (and report.md's) give the verdict: which node
   dropped frames, how many of how many, and the likely cause from the node's own
   ``/diagnostics`` (processing time against the input period, frames dropped by
   reason, input lost on the way). Exit codes: ``EXIT_CODES``.

The pictures of one frame (bird's-eye boxes, segmentation) show the frame nearest the
middle that every node answered; if there is none, the summary and the report say so.

Latency: from the publication of a frame's last input by the player to the reception of
the node's output by the recorder (the middleware's source and reception timestamps).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from functools import partial
from pathlib import Path

import numpy as np
from lidar_quality_core.time_sync import stamp_of_bytes

DEFAULT_DATA = Path("data/perception/demo")
# 4, not 3: scripts/loopback_guard.sh exits 3 for DDS traffic off loopback
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_DROPPED = 0, 1, 2, 4
EXIT_CODES = f"""exit codes:
  {EXIT_OK}  every node answered its frames (drops within --max-drop-fraction are said)
  {EXIT_FAILED}  failed: a node died, produced nothing, or published an output that does not
     match its input; or the nodes / the player did not run (before code {EXIT_DROPPED})
  {EXIT_USAGE}  bad arguments (no perception bag at --bag)
  {EXIT_DROPPED}  ran, but a node dropped more than --max-drop-fraction of its frames: the
     summary's and report.md's first lines name the node, the frames dropped of how
     many, and the likely cause"""
#: what a node's ``dropped.<reason>`` diagnostics counter means
DROP_REASONS = {
    "overrun": "waiting frame(s) dropped because processing fell behind the input (overrun)",
    "malformed_cloud": "frame(s) with a malformed input cloud",
    "undecodable_input": "input message(s) that could not be decoded",
    "invalid_stamp": "input message(s) with an invalid header stamp",
    "processing_error": "frame(s) lost to a processing error (see the node log)",
    "no_head": "frame(s) without a message of any head"}

def wiring(num_heads: int = 2, autoware: bool = False) -> dict:
    """node -> (parameter overrides, remaps input -> bag topic); ``autoware``: LMD and MIMO
    read their detections as DetectedObjects (``input_type: autoware``)."""
    heads = {}
    for k in range(num_heads):
        heads[f"input/head_{k}"] = f"/perception/head_{k}"
        heads[f"input/head_{k}/variance"] = f"/perception/head_{k}/variance"
    sim = {"use_sim_time": "true"}
    aw = {**sim, "input_type": "autoware"} if autoware else sim
    return {
        "lmd": (aw, {"input/points": "/lidar/points",
                      "input/detections": "/perception/detections",
                      "input/proposals": "/perception/proposals"}),
        "lms": ({**sim, "separate_probabilities": "true"},
                {"input/points": "/lidar/points",
                 "input/probabilities": "/perception/segmentation"}),
        "mimo": (aw, heads),
    }


def autoware_topic(topic: str) -> str:
    """A node's detections output as it is named in Autoware mode (output/objects)."""
    return topic.replace("output/detections", "output/objects")


def autoware_outputs(outputs: dict) -> dict:
    """``process.OUTPUTS`` with LMD's and MIMO's detections as Autoware's output/objects."""
    objects = "autoware_perception_msgs/msg/DetectedObjects"
    return {n: tuple((autoware_topic(t), objects) if t.endswith("output/detections")
                     else (t, typ) for t, typ in outs)
            for n, outs in outputs.items()}


def autoware_bag(bag: Path, say=print) -> Path:
    """The Autoware twin of perception bag ``bag`` (``<folder>_autoware/<name>``: its
    Detection3DArray topics as DetectedObjects), converted once and reused."""
    from .autoware_bag import FORMAT, convert

    twin = bag.parent.with_name(bag.parent.name + "_autoware") / bag.name
    stamp = twin.parent / f"{bag.name}.format"  # the conversion's version, beside the bag
    done = twin / "metadata.yaml"
    if (not done.is_file() or done.stat().st_mtime < (bag / "metadata.yaml").stat().st_mtime
            or not stamp.is_file() or stamp.read_text() != FORMAT):
        say(f"demo: converting {bag}'s detections to Autoware DetectedObjects into {twin}")
        twin.parent.mkdir(parents=True, exist_ok=True)
        convert(bag, twin)
        stamp.write_text(FORMAT)
    return twin


class Recorder:
    """Raw subscriptions to the nodes' outputs, written to a bag (log time = header stamp),
    with the middleware's reception time of each (topic, stamp) [ns, system clock]: taken
    when the sample arrived, not when this process got round to it."""

    def __init__(self, node, bag_path: Path, record: dict[str, str]):
        from lidar_quality_ros.bag_io import BagWriter, message_class
        from lidar_quality_ros.qos import output_qos
        from lidar_quality_ros.synced_inputs import InputReader, ReadByInputReader

        self.lock = threading.Lock()
        self.received: dict[str, dict[int, int]] = {t: {} for t in record}
        self.writer = BagWriter(bag_path)
        self.writer.__enter__()
        self.closed = False
        self._qos = output_qos(50)
        group = ReadByInputReader()
        self.subs = {topic: node.create_subscription(
            message_class(msgtype), topic, partial(self._on, topic, msgtype), self._qos, raw=True,
            callback_group=group) for topic, msgtype in record.items()}
        # read on a thread of its own, not by the harness's executor (which rebuilds its
        # wait set on every message: this process's CPU is taken from the nodes')
        self.reader = InputReader(node, list(self.subs.values()), "demo_recorder",
                                  lambda text: node.get_logger().error(
                                      f"recorder: {text}", throttle_duration_sec=5.0))

    def _on(self, topic: str, msgtype: str, data: bytes, info: dict) -> None:
        stamp = stamp_of_bytes(data)
        with self.lock:
            self.received[topic].setdefault(stamp, info["received_timestamp"])
            if not self.closed:
                self.writer.write(topic, msgtype, stamp, data, qos=[self._qos])

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self.received[topic])

    def close(self) -> None:
        self.reader.stop()
        with self.lock:
            if not self.closed:
                self.closed = True
                self.writer.__exit__(None, None, None)


def publish_times(bag: Path, log: Path) -> dict[str, dict[int, int]]:
    """topic -> header stamp -> system time [ns] of the player's publish call, from its
    ``--publish-log`` (bag topic, log time) and the bag (log time -> header stamp)."""
    from lidar_quality_ros.bag_io import read_bag

    rows = [line.split() for line in log.read_text().splitlines()]
    wall = {(t, int(log_ns)): int(w) for t, log_ns, w in rows}
    out: dict[str, dict[int, int]] = {}
    for m in read_bag(bag, {t for t, _ in wall}):
        w = wall.get((m.topic, m.stamp_ns))
        if w is not None:
            out.setdefault(m.topic, {}).setdefault(stamp_of_bytes(m.raw), w)
    return out


#: Frames at the start of the replay left out of the steady-state latency (one-time costs
#: of a node's first frames: lazy imports, the models' first predictions).
WARMUP_FRAMES = 10
#: The player's max_lateness: a message this much behind schedule shifts the rest of the
#: playback (a stall of the player, e.g. on a busy machine, would otherwise burst the late
#: frames into the nodes, which no live sensor does; shifts are reported in the summary).
MAX_LATENESS_S = 0.05


def latencies(published: dict, inputs: list[str], received: dict[int, int]) -> np.ndarray:
    """[ms] per output frame, in stamp order: its reception - the publication of the
    frame's last input."""
    ins = [published.get(t, {}) for t in inputs]
    return np.array([(received[s] - max(d[s] for d in ins)) / 1e6 for s in sorted(received)
                     if all(s in d for d in ins)])


def cpu_per_frame(cpu0: dict, cpu1: dict, player: dict, frames: int) -> dict:
    """Process CPU time (all threads, user + system) per played frame [ms]: the player (first
    to last publication), each node and the recorder (this process: recording, /diagnostics)
    from the start of the replay to the last output; ``total`` of them all."""
    if not frames:
        return {}
    out = {"player": player.get("cpu_s")}
    for n in cpu0:
        a, b = cpu0[n], cpu1.get(n)
        out[n] = None if a is None or b is None else b - a
    out = {n: (round(v / frames * 1e3, 1) if v is not None else None) for n, v in out.items()}
    out["total"] = round(sum(v for v in out.values() if v is not None), 1)
    return out


def run_live(bag: Path, out: Path, *, rate: float = 1.0, say=print,
             autoware: bool = False) -> dict:
    """Steps 2-3: start the nodes, replay ``bag``, record. Returns the live figures.
    ``autoware``: ``bag`` carries DetectedObjects (``autoware_bag``), LMD and MIMO read and
    write them."""
    from diagnostic_msgs.msg import DiagnosticArray
    from lidar_quality_ros.bag_io import bag_info
    from lidar_quality_tools.load_test import (NODES, DiagnosticsLog, cpu_seconds, node_command,
                                                  percentile)
    from lidar_quality_ros.perception_bag import head_count
    from lidar_quality_ros.qos import output_qos
    from lidar_quality_ros.testing import RosHarness

    info = bag_info(bag)
    wire = wiring(head_count(bag), autoware)
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    played = sorted({t for _, remaps in wire.values() for t in remaps.values()})
    missing = [t for t in played if t not in info.topics]
    if missing:
        raise SystemExit(f"demo: {bag} lacks {missing}: not a perception bag "
                         "(reference_perception.cli bag / split)")
    from .process import OUTPUTS  # what the nodes publish (process_bag writes the same)

    outputs = autoware_outputs(OUTPUTS) if autoware else OUTPUTS
    record = {topic: typ for outs in outputs.values() for topic, typ in outs}
    users = {t: sum(t in r.values() for _, r in wire.values()) for t in played}
    live: dict = {"nodes": {}}
    with RosHarness(num_threads=1) as ros:
        say(f"demo: ROS domain {ros.domain_id} (loopback only); starting lmd_node, lms_node, "
            "mimo_node")
        procs, params = {}, {}
        for name, (p, remaps) in wire.items():
            argv, params[name] = node_command(name, params=p, remaps=remaps)
            with open(logs / f"{name}_node.log", "w") as fh:  # the child keeps its own copy
                procs[name] = ros.spawn(argv, stdout=fh, stderr=subprocess.STDOUT,
                                        extra_env={"PYTHONFAULTHANDLER": "1"})
        diag = DiagnosticsLog()
        ros.node.create_subscription(DiagnosticArray, "/diagnostics", diag, output_qos(50))
        rec = Recorder(ros.node, out / "outputs", record)
        try:
            deadline = time.monotonic() + 120.0
            while any(ros.node.count_subscribers(t) < n for t, n in users.items()):
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs.values()):
                    raise RuntimeError(f"the nodes did not subscribe to {played} (exit codes "
                                       f"{ {n: p.poll() for n, p in procs.items()} }; logs in "
                                       f"{logs})")
                time.sleep(0.1)
            for topic, sub in rec.subs.items():
                if not ros.wait_for_match(sub, timeout=120.0):
                    dead = {n: p.poll() for n, p in procs.items() if p.poll() is not None}
                    raise RuntimeError(f"no publisher of {topic} after 120 s (exited: {dead}; "
                                       f"logs in {logs})")
            player_json = out / "player.json"
            from ament_index_python.packages import get_package_prefix
            exe = Path(get_package_prefix("lidar_quality_ros")) / "lib" / "lidar_quality_ros" / "bag_player"
            argv = [str(exe), str(bag), "--topics", *played, "--rate", str(rate),
                    "--wait-for-subscribers", "1", "--wait-timeout", "60",
                    # a stall of the player delays the rest of the bag, as it would a live
                    # sensor, instead of bursting the late frames into the nodes (reported)
                    "--max-lateness", str(MAX_LATENESS_S),
                    "--summary-json", str(player_json), "--publish-log", str(logs / "published.txt")]
            # A bag written moments ago (generated, converted) sits in the page cache as
            # dirty pages (700 MB for the demo) that the kernel writes back ~30 s later, in
            # the middle of the replay, taking CPU from the player and the nodes: flush now.
            t_sync = time.monotonic()
            os.sync()
            live["sync_s"] = round(time.monotonic() - t_sync, 2)
            say(f"demo: replaying {bag} ({info.topics['/lidar/points'].count} frames, "
                f"{len(played)} topics) at rate {rate:g} with /clock")
            t0 = time.monotonic()
            cpu0 = {n: cpu_seconds(p.pid) for n, p in procs.items()}
            cpu0["recorder"] = time.process_time()
            with open(logs / "bag_player.log", "w") as fh:
                player = ros.spawn(argv, stdout=fh, stderr=subprocess.STDOUT)
            duration = (info.end_ns - info.start_ns) / 1e9
            try:
                player.wait(timeout=120 + 3 * duration / rate)
            except subprocess.TimeoutExpired:
                player.kill()
                raise RuntimeError(f"bag_player did not finish (log {logs / 'bag_player.log'})")
            if player.returncode:
                raise RuntimeError(f"bag_player exited with {player.returncode} "
                                   f"(log {logs / 'bag_player.log'})")
            live["wall_s"] = round(time.monotonic() - t0, 1)
            live["player"] = json.loads(player_json.read_text())
            # the last frames' outputs: wait until nothing new arrives for 3 s
            last, quiet = -1, time.monotonic()
            while time.monotonic() - quiet < 3.0:
                n = sum(rec.count(t) for t in record)
                if n != last:
                    last, quiet = n, time.monotonic()
                time.sleep(0.2)
            cpu1 = {n: cpu_seconds(p.pid) for n, p in procs.items()}
            cpu1["recorder"] = time.process_time()
            time.sleep(1.5)  # one more diagnostics period
            diag_values = {n: diag.values(n) for n in wire}
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            codes = {}
            for n, p in procs.items():
                try:
                    codes[n] = p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    codes[n] = "killed (no exit 30 s after SIGINT)"
            rec.close()
    published = {t: v["count"] for t, v in live["player"]["topics"].items()}
    live["cpu_ms_per_frame"] = cpu_per_frame(cpu0, cpu1, live["player"],
                                             published.get("/lidar/points", 0))
    pub_times = publish_times(bag, logs / "published.txt")
    # the period the player keeps: the clouds' stamps at ``rate`` (its publish times
    # jitter with the load, a few frames' median among them)
    clouds = np.sort(np.fromiter(pub_times.get("/lidar/points", {}).keys(), float))
    live["input_period_ms"] = round(float(np.median(np.diff(clouds))) / 1e6 / rate, 1) \
        if len(clouds) > 1 else None
    for name, (_, remaps) in wire.items():
        inputs = list(remaps.values())
        main = f"/{name}/{NODES[name][1]}"  # the node's main output
        if autoware:
            main = autoware_topic(main)
        lat = latencies(pub_times, inputs, rec.received[main])
        frames_in = min(published.get(t, 0) for t in inputs)
        frames_out = rec.count(main)
        live["nodes"][name] = {
            "frames_in": frames_in, "frames_out": frames_out,
            "dropped": frames_in - frames_out,
            "latency_ms_p50": percentile(lat, 50), "latency_ms_p99": percentile(lat, 99),
            "latency_ms_max": round(float(lat.max()), 2) if len(lat) else None,
            # after the first WARMUP_FRAMES frames
            "latency_ms_p99_steady": percentile(lat[WARMUP_FRAMES:], 99),
            "latency_ms_first_frames": [round(float(x), 1) for x in lat[:WARMUP_FRAMES]],
            "node_diagnostics": {k: v for k, v in diag_values[name].items()
                                 if k.startswith(("dropped", "frames", "latency", "received",
                                                  "sync.", "processing_ms"))},
            # the node's input name -> the bag topic on it and the messages published
            "inputs": {k: {"topic": t, "published": published.get(t, 0)}
                       for k, t in remaps.items()},
            "exit_code": codes[name], "log": str(logs / f"{name}_node.log")}
        live["nodes"][name]["_latencies"] = lat
    live["params"] = params
    return live


def _settings(params: dict):
    """LMS and MIMO settings as the nodes built them from their parameters."""
    from .process import node_settings

    return node_settings("lms", params["lms"]), node_settings("mimo", params["mimo"])


def _num(d: dict, *keys) -> float | None:
    """The first of ``keys`` in ``d`` as a number (diagnostics values are strings)."""
    for k in keys:
        try:
            return float(d[k])
        except (KeyError, TypeError, ValueError):
            continue
    return None


def likely_causes(v: dict, input_period_ms: float | None) -> list[str]:
    """Why a node lost frames, from its ``/diagnostics`` (``v``: a node of the summary):
    the CPU (frames dropped as overrun, or processing slower than the input period with
    drops the node's reasons do not explain), its drop reasons, input lost before the
    node, inputs not matched by stamp, outputs lost after it."""
    d = v.get("node_diagnostics") or {}
    if not d:
        return [f"unknown: the node published no /diagnostics (see {v.get('log', 'its log')})"]
    causes = []
    reasons = {k.split(".", 1)[1]: int(n) for k, n in d.items()
               if k.startswith("dropped.") and _num(d, k)}
    p50, p99 = _num(d, "processing_ms_p50"), _num(d, "processing_ms_p99")
    unexplained = v["frames_in"] - v["frames_out"] > sum(
        n for r, n in reasons.items() if r != "overrun")
    slow = p99 is not None and input_period_ms and p99 > input_period_ms and unexplained
    if "overrun" in reasons or slow:
        cpu = "CPU: processing " + (f"p50 {p50:.0f} ms / p99 {p99:.0f} ms" if p99 is not None
                                    else "time unknown")
        if input_period_ms:
            cpu += f" against an input period of {input_period_ms:.0f} ms"
        if "overrun" in reasons:
            cpu += f"; {reasons.pop('overrun')} {DROP_REASONS['overrun']}"
        causes.append(cpu)
    causes += [f"{n} {DROP_REASONS.get(r, r)}" for r, n in sorted(reasons.items())]
    ns = "/" + v["node"] if "node" in v else ""
    lost = []
    for key, inp in (v.get("inputs") or {}).items():
        got = _num(d, f"received.{key}", f"received.{inp['topic']}", f"received.{ns}/{key}")
        if got is not None and got < inp["published"]:
            lost.append(f"{got:.0f} of {inp['published']} on {inp['topic']}")
    if lost:
        causes.append("input lost on the way: received " + ", ".join(lost))
    for kind in ("late", "dropped"):
        unmatched = [f"{n} on {k.split('.', 2)[2]}" for k, n in sorted(d.items())
                     if k.startswith(f"sync.{kind}.") and _num(d, k)]
        if unmatched:
            causes.append(f"stamp matching: message(s) {kind} ({', '.join(unmatched)}): a "
                          "frame's inputs came too late or not at all")
    node_out = _num(d, "frames_out")
    if node_out is not None and node_out > v["frames_out"]:
        causes.append(f"outputs lost on the way: the node published {node_out:.0f}, the "
                      f"recorder received {v['frames_out']}")
    return causes or [f"none in the node's diagnostics (see {v.get('log', 'its log')})"]


def verdict(nodes: dict, *, max_drop_fraction: float = 0.05,
            input_period_ms: float | None = None) -> tuple[int, list[str]]:
    """(exit code, lines) of a run from its nodes' figures (the summary's ``nodes``):
    ``EXIT_FAILED`` when a node died, produced nothing or published mismatched outputs;
    else ``EXIT_DROPPED`` when a node dropped more than ``max_drop_fraction`` of its
    frames. Every drop is said, with its likely cause, whatever the code."""
    failed, over, lines = [], [], []
    for n, v in nodes.items():
        why = []
        if v.get("exit_code") != 0:
            why.append(f"exited with {v.get('exit_code')}")
        if not v["frames_out"]:
            why.append("produced nothing")
        if v.get("mismatched"):
            why.append(f"published {v['mismatched']} output(s) that do not match their input")
        if why:
            failed.append(n)
            lines.append(f"FAILED: {n}_node {', '.join(why)} (log {v.get('log', '-')})")
    for n, v in nodes.items():
        f_in, f_out = v["frames_in"], v["frames_out"]
        dropped = f_in - f_out
        own = _num(v.get("node_diagnostics") or {}, "dropped") or 0
        if dropped <= 0 and not own:
            continue
        causes = "; ".join(likely_causes({"node": n, **v}, input_period_ms))
        if dropped <= 0:
            lines.append(f"note: {n}_node answered all {f_in} frames, but its diagnostics "
                         f"count {own:.0f} dropped: {causes}")
            continue
        frac = dropped / f_in if f_in else 1.0
        if frac > max_drop_fraction:
            over.append(n)
            head = (f"FRAMES DROPPED: {n}_node dropped {dropped} of {f_in} frames ({frac:.1%} "
                    f"> {max_drop_fraction:.1%} allowed)")
        else:
            head = (f"note: {n}_node dropped {dropped} of {f_in} frames ({frac:.1%}, within "
                    f"the {max_drop_fraction:.1%} allowed)")
        lines.append(f"{head}; likely cause: {causes}")
    code = EXIT_FAILED if failed else EXIT_DROPPED if over else EXIT_OK
    if code == EXIT_OK and not lines:
        lines.append("OK: every node answered every frame (0 dropped)")
    elif code == EXIT_OK:
        lines.append(f"OK: no node dropped more than {max_drop_fraction:.1%} of its frames")
    return code, lines


def picture_note(ev) -> str:
    """Which frame the pictures show, or that there is none (``ev``: the Evaluation)."""
    if ev.example_frame is None:
        return ("no frame was answered by every node: no bird's-eye or segmentation "
                "picture")
    if ev.example_frame == ev.example_target:
        return f"pictures: frame {ev.example_frame} (the middle one; every node answered it)"
    return (f"pictures: frame {ev.example_frame}, the nearest to the middle frame "
            f"{ev.example_target} that every node answered "
            f"({ev.answered_by_all} of {ev.frames} frames were)")


def write_report(out: Path, summary: dict, ev, live: dict) -> list[Path]:
    """``report.md`` and the PNG plots; returns the plots."""
    from lidar_quality_core import report_plots as rp
    from lidar_quality_core.pointcloud import xyz_intensity

    from .evaluation import BASELINES

    figs = []
    names = {"lmd": "LMD", "lms": "LMS", "mimo": "MIMO"}
    for m, r in ev.rows.items():
        tp, conf, base = r.column("tp"), r.column("confidence"), r.column("baseline")
        ok = np.isfinite(conf) & np.isfinite(base)
        if ok.sum() < 2:
            continue
        figs.append(rp.reliability_png(out / f"{m}_reliability.png", {
            f"{names[m]} confidence": (tp[ok], conf[ok]), BASELINES[m]: (tp[ok], base[ok])},
            title=f"{names[m]}: reliability of the recorded confidence vs {BASELINES[m]}"))
        figs.append(rp.scatter_png(out / f"{m}_iou_scatter.png", r.column("iou"),
                                   r.column("predicted_iou"), title=f"{names[m]} predicted IoU",
                                   xlabel="true IoU" + (" (adjusted)" if m == "lms" else "")))
    ex = ev.example.get("lmd")
    if ex is not None:
        xyz, _ = xyz_intensity(ex["points"])
        figs.append(rp.bev_boxes_png(
            out / "lmd_bev_frame.png", xyz[:, :2], ex["boxes"], ex["confidence"],
            gt_boxes=ex["gt_boxes"], title=f"LMD, frame {ex['frame']}: boxes by meta confidence\n"
                                           "(dashed: ground truth)"))
    ex = ev.example.get("lms")
    if ex is not None:
        res, inp = ex["result"], ex["input"]
        seg = res.point_segment
        pred = np.full(res.n_segments, np.nan)
        true = np.full(res.n_segments, np.nan)
        sid = np.asarray(ex["segment_ids"])
        pred[sid], true[sid] = ex["predicted_iou"], ex["iou"]
        has = seg >= 0
        per_pred = np.where(has, pred[np.maximum(seg, 0)], np.nan)
        per_true = np.where(has, true[np.maximum(seg, 0)], np.nan)
        figs.append(rp.bev_values_png(
            out / "lms_segmentation_frame.png", inp.xyz[:, :2],
            {"predicted IoU (LMS node)": per_pred, "true IoU_adj": per_true},
            label="segment IoU", title=f"LMS, frame {ex['frame']}: segments coloured by IoU"))
    lat = {names[n]: v["_latencies"] for n, v in live["nodes"].items()}
    figs.append(rp.histogram_png(out / "latency.png", lat, xlabel="latency [ms] (last input "
                                 "published -> output received)", title="Per-frame latency over DDS"))
    (out / "report.md").write_text(report_markdown(summary, figs))
    return figs


def report_markdown(summary: dict, figs: list[Path]) -> str:
    from lidar_quality_training.report import markdown_table

    from .evaluation import BASELINES

    s = summary
    v = s["verdict"]
    meaning = {EXIT_OK: "ok", EXIT_FAILED: "failed", EXIT_DROPPED: "frames dropped"}
    L = ["# Demo report", "", f"**Exit code {v['exit_code']} "
         f"({meaning.get(v['exit_code'], '?')})**", ""]
    L += [f"- {x}" for x in v["lines"] + [v["pictures"]]] + [""]
    L += [f"Bag `{s['bag']}`: {s['frames']} frames replayed in real time (rate {s['rate']:g}) "
         f"into lmd_node, lms_node and mimo_node (separate processes, `use_sim_time`), "
         f"outputs recorded to `{s['outputs_bag']}` and evaluated against the ground truth." + (
             f" The player stalled: its schedule was shifted {s['player']['shifts']} times, "
             f"{s['player']['shifted_ms']} ms in all (frames delayed, not burst)."
             if s.get("player", {}).get("shifts") else ""),
         "", "## Frames and latency", "",
         markdown_table(["node", "frames in", "frames out", "dropped", "latency p50 [ms]",
                         "latency p99 [ms]", f"p99 after frame {WARMUP_FRAMES} [ms]", "exit"],
                        [[n, v["frames_in"], v["frames_out"], v["dropped"],
                          v["latency_ms_p50"], v["latency_ms_p99"], v["latency_ms_p99_steady"],
                          v["exit_code"]]
                         for n, v in s["nodes"].items()],
                        digits=1),
         "Latency: from the publication of a frame's last input (bag player) to the "
         "reception of the node's output (recorder), by the middleware's timestamps; the "
         f"steady p99 leaves out the first {WARMUP_FRAMES} frames (one-time start-up costs).",
         "",
         "## Quality of the recorded estimates", "",
         markdown_table(["node", "rows", "AUROC", "AUROC baseline", "ECE", "ECE baseline", "R²",
                         "baseline"],
                        [[n, v["n"], v["auroc"], v["auroc_baseline"], v["ece"], v["ece_baseline"],
                          v["r2"], BASELINES[n]] for n, v in s["nodes"].items()]),
         "Rows: LMD detections, LMS segments with a defined IoU_adj, MIMO merged boxes. "
         "True positive: LMD BEV IoU >= 0.5 with any ground-truth box; MIMO with one of "
         "its class; LMS IoU_adj > 0. R²: predicted against true IoU.", ""]
    bad = {n: v for n, v in s["nodes"].items() if v.get("mismatched")}
    if bad:
        L += [f"Mismatched outputs (left out): {({n: v['mismatched'] for n, v in bad.items()})}", ""]
    L += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in figs] + [""]
    return "\n".join(L)


def print_summary(s: dict) -> None:
    mode = (" (LMD and MIMO on Autoware DetectedObjects)" if s.get("mode") == "autoware"
            else "")
    print(f"\ndemo: {s['frames']} frames of {s['bag']}{mode}; report {s['report']}")
    for line in s["verdict"]["lines"] + [s["verdict"]["pictures"]]:
        print(f"demo: {line}")
    cpu = s.get("cpu_ms_per_frame") or {}
    if cpu:
        print("demo: CPU per frame [ms]: " + ", ".join(
            f"{n} {v if v is not None else '-'}" for n, v in cpu.items() if n != "total")
            + f"; total {cpu['total']} ({os.cpu_count()} cores: "
            f"{os.cpu_count() * (s['input_period_ms'] or 0):.0f} ms per input period)")
    pl = s.get("player") or {}
    if pl.get("shifts"):
        print(f"demo: the player stalled: schedule shifted {pl['shifts']} times, "
              f"{pl['shifted_ms']} ms in all (frames delayed, not burst)")
    print(f"{'node':5s} {'in':>5s} {'out':>5s} {'drop':>5s} {'p50 ms':>7s} {'p99 ms':>7s} "
          f"{'steady':>7s} {'AUROC':>6s} {'(base)':>7s} {'ECE':>6s} {'(base)':>7s} {'R2':>6s}  baseline")

    def f(x, w, d=3):
        return f"{x:{w}.{d}f}" if isinstance(x, (int, float)) and x is not None else f"{'-':>{w}s}"

    from .evaluation import BASELINES
    for n, v in s["nodes"].items():
        print(f"{n:5s} {v['frames_in']:5d} {v['frames_out']:5d} {v['dropped']:5d} "
              f"{f(v['latency_ms_p50'], 7, 1)} {f(v['latency_ms_p99'], 7, 1)} "
              f"{f(v['latency_ms_p99_steady'], 7, 1)} "
              f"{f(v['auroc'], 6)} {f(v['auroc_baseline'], 7)} {f(v['ece'], 6)} "
              f"{f(v['ece_baseline'], 7)} {f(v['r2'], 6)}  {BASELINES[n]}")


def main(argv=None) -> int:
    from lidar_quality_core.jsonable import jsonable
    from lidar_quality_ros.perception_bag import resolve_bags

    from .evaluation import evaluate

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=EXIT_CODES,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", type=Path, default=DEFAULT_DATA,
                    help="perception bag, or a folder of them (the first is used)")
    ap.add_argument("--out", type=Path, default=Path("out/demo"))
    ap.add_argument("--rate", type=float, default=1.0, help="playback speed")
    ap.add_argument("--autoware", action="store_true",
                    help="LMD and MIMO read and write Autoware's DetectedObjects (the bag's "
                    "detections converted once into <bag folder>_autoware)")
    ap.add_argument("--max-drop-fraction", type=float, default=0.05, metavar="F",
                    help=f"exit {EXIT_DROPPED} when a node drops more than this fraction of its "
                    "frames (default 0.05; every drop is reported)")
    a = ap.parse_args(argv)
    if not 0 <= a.max_drop_fraction <= 1:
        ap.error(f"--max-drop-fraction {a.max_drop_fraction}: expected a fraction in [0, 1]")
    try:
        bag = resolve_bags([a.bag])[0]
    except (ValueError, FileNotFoundError, IndexError) as e:
        print(f"demo: no perception bag at {a.bag} ({e}); `make demo` generates it "
              "(make data/perception/demo/.done)", file=sys.stderr)
        return EXIT_USAGE
    if not os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"):
        print("demo: warning: FASTRTPS_DEFAULT_PROFILES_FILE is unset (run through "
              "scripts/with_env.sh): large clouds may be lost between processes", file=sys.stderr)
    out = a.out
    if (out / "outputs").exists():
        import shutil
        shutil.rmtree(out / "outputs")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    played = bag
    try:
        if a.autoware:
            played = autoware_bag(bag)
        live = run_live(played, out, rate=a.rate, autoware=a.autoware)
    except RuntimeError as e:
        print(f"demo: FAILED: {e}", file=sys.stderr)
        return EXIT_FAILED
    print("demo: evaluating the recorded outputs against the ground truth", flush=True)
    lms_s, mimo_s = _settings(live["params"])
    # inputs and ground truth from the original bag (the Autoware twin holds the same boxes)
    ev = evaluate(bag, out / "outputs", lms_settings=lms_s, mimo_settings=mimo_s,
                  autoware=a.autoware)
    q = ev.quality()
    summary = {"bag": str(bag), "frames": ev.frames, "rate": a.rate,
               "mode": "autoware" if a.autoware else "vision_msgs", "played": str(played),
               "outputs_bag": str(out / "outputs"), "report": str(out / "report.md"),
               "player": {k: live["player"][k] for k in ("achieved_rate", "late_ms_p99",
                                                         "wall_s", "shifts", "shifted_ms")},
               "input_period_ms": live["input_period_ms"],
               "sync_s": live.get("sync_s"),  # flushing dirty pages before the replay
               "cpu_ms_per_frame": live["cpu_ms_per_frame"],
               # frames in / out as played and recorded (the evaluation's: frames_scored)
               "nodes": {n: {**q[n], "frames_scored": q[n]["frames_out"],
                             **{k: v for k, v in live["nodes"][n].items()
                                if not k.startswith("_")}} for n in live["nodes"]}}
    code, lines = verdict(summary["nodes"], max_drop_fraction=a.max_drop_fraction,
                          input_period_ms=live["input_period_ms"])
    summary["verdict"] = {"exit_code": code, "max_drop_fraction": a.max_drop_fraction,
                          "lines": lines, "pictures": picture_note(ev),
                          "picture_frame": ev.example_frame}
    write_report(out, summary, ev, live)
    summary["elapsed_s"] = round(time.monotonic() - t0, 1)
    (out / "summary.json").write_text(json.dumps(jsonable(summary), indent=1))
    print_summary(summary)
    if code == EXIT_FAILED:
        print(f"demo: exit {code} (failed): " + " | ".join(
            x[len("FAILED: "):] for x in lines if x.startswith("FAILED")), file=sys.stderr)
    elif code == EXIT_DROPPED:
        over = [f"{n}_node {v['dropped']} of {v['frames_in']}"
                for n, v in summary["nodes"].items()
                if v["dropped"] > a.max_drop_fraction * v["frames_in"]]
        print(f"demo: exit {code} (frames dropped: {', '.join(over)}; causes above; logs in "
              f"{out / 'logs'})", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
