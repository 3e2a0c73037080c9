#!/usr/bin/env python3
"""Fuzz lmd_node, lms_node and mimo_node with malformed input (issue 8, hardening).

Per node: start it in-process in a private ROS world (``lidar_quality_ros.testing.
RosHarness``) with the parameters of its installed config file and every optional input
enabled; send a valid reference frame; then ``--cases`` malformed frames from
``lidar_quality_tools.fuzz`` over all its input topics with the sensor-data QoS, one at a
time (each settles, received and processed or dropped, before the next); then valid
frames again. A node passes when no callback raised into the executor (the executable
would have died), its frame worker is alive, the valid frame after the garbage is
processed with the same outputs as before it (stamps aside), and every processed
malformed frame kept the node's output invariant (LMD: same ids in the same order; LMS:
one output point per input point; MIMO: at most one merged box per input box).

Each node runs in a child process, so a crash of one cannot hide the others; the merged
report goes to ``--out`` (JSON) and a table to stdout. Exit code 0 iff every node passed.

    bash scripts/with_env.sh python scripts/fuzz_nodes.py                # 10,000 per node
    bash scripts/with_env.sh python scripts/fuzz_nodes.py --cases 300 --nodes lmd
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict, deque
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: node -> (package, module, class, overrides enabling every optional input, optional
#: overrides dropped if the node refuses them, e.g. a model variant that is not shipped).
#: ``lms_separate`` is lms_node with the probabilities on their own topic.
NODES = {
    "lmd": ("lmd_ros", "lmd_ros.lmd_node", "LmdNode", {"proposal_mode": "threshold"}, {}),
    "lms": ("lms_ros", "lms_ros.lms_node", "LmsNode", {}, {}),
    "lms_separate": ("lms_ros", "lms_ros.lms_node", "LmsNode",
                     {"separate_probabilities": True}, {}),
    "mimo": ("mimo_ros", "mimo_ros.mimo_node", "MimoNode", {"use_variances": True},
             {"use_points": True}),
}
#: Parameter naming a node's classes (LMS: probability fields; LMD, MIMO: hypotheses).
CLASS_PARAM = "class_names"


# ---------------------------------------------------------------------------- node I/O
def input_specs(node, name: str):
    """InputSpecs of the node's synchronised inputs, from its subscriptions."""
    from lidar_quality_tools.fuzz import input_spec
    from reference_perception.messages import probability_field
    types = {s.topic_name: s.msg_type for s in node.subscriptions}
    probs, separate = (), False
    if name.startswith("lms"):
        probs = tuple(probability_field(c) for c in node.get_parameter(CLASS_PARAM).value)
        separate = bool(node.get_parameter("separate_probabilities").value)
    return [input_spec(t, types[node.resolve_topic_name(t)].__name__, probs, separate)
            for t in node.inputs.topics]


def _stamp_key(msg) -> tuple[int, int] | None:
    """(sec, nanosec) of a message; a MarkerArray's is that of its first stamped marker."""
    if not hasattr(msg, "header"):
        stamps = [m.header.stamp for m in getattr(msg, "markers", ())
                  if m.header.stamp.sec or m.header.stamp.nanosec]
        return (int(stamps[0].sec), int(stamps[0].nanosec)) if stamps else None
    return (int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))


#: the drift verdict of the window ending at a frame: it depends on the frames before (the
#: fuzzed ones among them) by design, so it is not part of a frame's own output
WINDOW_FIELDS = frozenset({"drift_level", "drift_score", "drift_window_frames",
                           "drift_quantities"})


def difference(a, b, path: str = "") -> str | None:
    """First difference between two messages, stamps (builtin_interfaces/Time) and the
    drift window's fields (``WINDOW_FIELDS``) ignored and NaN equal to NaN; None when they
    have the same content."""
    import numpy as np
    if hasattr(a, "get_fields_and_field_types"):
        if type(a) is not type(b):
            return f"{path}: {type(a).__name__} vs {type(b).__name__}"
        for fname, ftype in a.get_fields_and_field_types().items():
            if ftype == "builtin_interfaces/Time" or fname in WINDOW_FIELDS:
                continue
            d = difference(getattr(a, fname), getattr(b, fname), f"{path}.{fname}")
            if d:
                return d
        return None
    if isinstance(a, (list, tuple)) and a and hasattr(a[0], "get_fields_and_field_types"):
        if len(a) != len(b):
            return f"{path}: {len(a)} vs {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            d = difference(x, y, f"{path}[{i}]")
            if d:
                return d
        return None
    if isinstance(a, (str, bytes, bool, int)) or a is None:
        return None if a == b else f"{path}: {a!r:.40} vs {b!r:.40}"
    x, y = np.asarray(a), np.asarray(b)
    if x.shape != y.shape:
        return f"{path}: shape {x.shape} vs {y.shape}"
    same = np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
    return None if same else f"{path}: values differ"


class OutputWatch:
    """Counts a node's outputs on one topic, keeps those of watched stamps and checks the
    per-frame invariant against what was sent for that stamp."""

    def __init__(self, topic: str):
        self.topic = topic
        self.count = 0
        self.keep: dict[tuple, object] = {}
        self.watch: set[tuple] = set()
        self.expect: dict[tuple, object] = {}   # stamp -> check(msg) -> error or None
        self.checked = 0
        self.violations: list[str] = []
        self.n_violations = 0
        self._lock = threading.Lock()

    def __call__(self, msg) -> None:
        key = _stamp_key(msg)
        with self._lock:
            self.count += 1
            if key in self.watch:
                self.keep[key] = msg
            check = self.expect.pop(key, None)
        if check is not None:
            err = check(msg)
            with self._lock:
                self.checked += 1
                if err:
                    self.n_violations += 1
                    if len(self.violations) < 10:
                        self.violations.append(f"{self.topic} @ {key}: {err}")

    def add_check(self, key, check, keep: int = 200) -> None:
        """Check the output of stamp ``key`` when it comes (the ``keep`` newest pending)."""
        with self._lock:
            self.expect.pop(key, None)
            self.expect[key] = check
            while len(self.expect) > keep:  # frames dropped by the node never come out
                self.expect.pop(next(iter(self.expect)))

    def drop_check(self, key) -> None:
        """Forget the pending check of stamp ``key`` (its frame is ambiguous)."""
        with self._lock:
            self.expect.pop(key, None)

    def wait(self, key, timeout: float) -> object | None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if key in self.keep:
                    return self.keep[key]
            time.sleep(0.01)
        return None


def invariant(name: str, topic: str, frame: dict):
    """check(msg) for output ``topic`` of a processed frame made of ``frame`` (topic ->
    message sent), or None where the node promises nothing checkable."""
    if name == "lmd" and topic.endswith("output/detections") and "input/detections" in frame:
        want = [d.id for d in frame["input/detections"].detections]
        return lambda m: (None if [d.id for d in m.detections] == want else
                          f"ids {[d.id for d in m.detections][:5]}.. != sent {want[:5]}.. "
                          f"({len(m.detections)} vs {len(want)})")
    if name.startswith("lms") and topic.endswith("output/points") and "input/points" in frame:
        c = frame["input/points"]
        n = c.width * c.height
        return lambda m: (None if m.width * m.height == n
                          else f"{m.width * m.height} points out, {n} in")
    if name == "mimo" and topic.endswith("output/detections"):
        n = sum(len(m.detections) for t, m in frame.items()
                if t.rsplit("/", 1)[-1].startswith("head_"))
        return lambda m: None if len(m.detections) <= n else f"{len(m.detections)} merged > {n} in"
    return None


# ---------------------------------------------------------------------------- counters
class Counters:
    """Snapshots of the node's diagnostics counters and its synchroniser's."""

    def __init__(self, node):
        self.node = node

    def snapshot(self) -> dict[str, int]:
        st = self.node.inputs.sync.stats()
        snap = self.node.diag.counts()
        snap.update(received=sum(v for k, v in snap.items() if k.startswith("received.")),
                    sync_received=sum(st.received), matched=st.matched, late=sum(st.late),
                    sync_dropped=sum(st.dropped), resets=st.resets)
        return snap

    @staticmethod
    def own_dropped(s: dict) -> int:
        return sum(v for k, v in s.items() if k.startswith("dropped."))


#: Drop reasons of SyncedInputs for a message that never reaches the synchroniser.
PRE_SYNC_DROPS = ("dropped.invalid_stamp", "dropped.undecodable_input")
#: cases after a corrupt one in which a refusal may still be that corrupt case's
LATE_REFUSAL_CASES = 2
#: what synced_inputs says when it counts a message as undecodable_input
REFUSALS = ("cannot decode it", "input reader:", "callback failed", "cannot take a message")


def settle(node, counters: Counters, before: dict, n_msgs: int, heavy: bool, state: dict,
           recv_timeout: float = 2.0):
    """Wait until the case's messages were received and every matched set is processed or
    dropped; returns (snapshot, messages lost in transport, settled in time)."""
    recv_deadline = time.monotonic() + (60.0 if heavy else recv_timeout)
    while True:
        s = counters.snapshot()
        got = s["received"] - before["received"]
        if got >= n_msgs or time.monotonic() > recv_deadline:
            break
        time.sleep(0.001)
    lost = max(n_msgs - got, 0)
    deadline = time.monotonic() + (300.0 if heavy else 10.0)
    while True:
        # every received message reached the synchroniser (or was dropped before it for
        # its stamp), and every matched set was processed or dropped
        seen = s["sync_received"] - before["sync_received"] + sum(
            s.get(k, 0) - before.get(k, 0) for k in PRE_SYNC_DROPS)
        lag = s["matched"] - s["frames_out"] - Counters.own_dropped(s)
        if seen >= got and lag <= state["lag_floor"] and node.inputs.worker.idle():
            return s, lost, True
        if time.monotonic() > deadline:
            # a set neither processed nor counted as dropped: accept it, go on
            state["lag_floor"] = max(state["lag_floor"], lag)
            return s, lost, False
        time.sleep(0.001)
        s = counters.snapshot()


# ---------------------------------------------------------------------------- one node
def fuzz_node(name: str, cases: int, seed: int, extra: dict, huge_clouds: int,
              box_floods: int | None) -> dict:
    from lidar_quality_tools import fuzz
    from lidar_quality_ros.params import config_parameters
    from lidar_quality_ros.qos import output_qos
    from lidar_quality_ros.testing import RosHarness

    package, module, cls_name, overrides, optional = NODES[name]
    node_cls = getattr(importlib.import_module(module), cls_name)
    params = config_parameters(package, f"{name.split('_')[0]}_node")
    report: dict = {"node": name, "cases": cases, "seed": seed, "started": False}
    t_start = time.monotonic()
    ros = RosHarness()
    try:
        node, used = None, None
        for opt in (optional, {}):
            used = {**params, **overrides, **opt, **extra.get(name, {})}
            try:
                node = ros.start(node_cls, parameters=used)
                break
            except Exception as exc:  # noqa: BLE001 - reported
                report.setdefault("start_errors", []).append(f"{type(exc).__name__}: {exc}")
                if not opt:
                    return report
        report["started"] = True
        report["parameters"] = {k: v for k, v in used.items() if k in overrides or k in optional
                                or k in extra.get(name, {}) or k.endswith("_path")}
        specs = input_specs(node, name)
        report["inputs"] = [s.topic for s in specs]
        classes = (tuple(node.get_parameter(CLASS_PARAM).value)
                   if not name.startswith("lms") and node.has_parameter(CLASS_PARAM)
                   else ("car", "truck", "pedestrian", "cyclist"))
        small = fuzz.FrameTemplate(specs, n_points=2000, n_objects=6, n_proposals=40,
                                   seed=seed, classes=classes)
        valid = fuzz.FrameTemplate(specs, n_points=20_000, n_objects=15, n_proposals=150,
                                   seed=seed + 7, classes=classes)
        fuzzer = fuzz.Fuzzer(small, seed, huge_clouds=huge_clouds, box_floods=box_floods)

        pubs = {s.topic: ros.sensor_publisher(type(small.messages[s.topic]), s.topic)
                for s in specs}
        ns = node.get_namespace().rstrip("/")
        outs = {}
        for pub in node.publishers:
            if pub.topic_name.startswith(f"{ns}/output/"):
                w = OutputWatch(pub.topic_name)
                w.subscription = ros.node.create_subscription(pub.msg_type, pub.topic_name, w,
                                                              output_qos(50))
                outs[pub.topic_name] = w
        report["outputs"] = sorted(outs)
        for topic, p in pubs.items():
            if not ros.wait_for_match(p, timeout=30.0):
                raise RuntimeError(f"{name}: nobody subscribes to {topic}")
        for w in outs.values():
            if not ros.wait_for_match(w.subscription, timeout=30.0):
                raise RuntimeError(f"{name}: no publisher on {w.topic}")

        def send_valid(stamp_ns: int):
            frame = valid.frame(stamp_ns)
            key = _stamp_key(next(iter(frame.values())))
            for w in outs.values():
                w.watch.add(key)
                chk = invariant(name, w.topic, frame)
                if chk is not None:
                    w.add_check(key, chk)
            for topic, msg in frame.items():
                pubs[topic].publish(msg)
            got = {t: w.wait(key, 60.0) for t, w in outs.items()}
            return frame, got

        # reference: the valid frame before any garbage
        ref_frame, ref = send_valid(fuzzer.start_ns - 1_000_000_000)
        missing = [t for t, m in ref.items() if m is None]
        if missing:
            raise RuntimeError(f"{name}: no output on {missing} for the reference frame")

        counters = Counters(node)
        state = {"lag_floor": 0}
        cats: dict[str, dict] = defaultdict(lambda: {"cases": 0, "malformed_messages": 0,
                                                     "outcomes": Counter(), "examples": {},
                                                     "seconds": 0.0, "max_case_s": 0.0})
        sent_msgs = malformed = unsettled = n_ambiguous = 0
        used_keys = {_stamp_key(m) for m in ref_frame.values()}
        # corrupt messages not refused in their own case: (case index, count). Another
        # case's late message can make a corrupt case look settled before its refusal is
        # counted (seen in CI); a corrupt message a decoder accepts is never refused, so
        # an entry expires after LATE_REFUSAL_CASES cases
        corrupt_pending: deque = deque()
        prev_category = None
        t_fuzz = time.monotonic()
        for case in fuzzer.cases(cases):
            heavy = case.category in fuzz.HEAVY_CATEGORIES
            before = counters.snapshot()
            frame = dict(case.messages)
            # invariants need the inputs as messages (corrupt_cdr sends bytes)
            typed = not any(isinstance(m, bytes) for m in frame.values())
            # checks are keyed by the stamp of the first input (outputs copy an input
            # header). After the clock went back, a stamp may come again: an output of
            # that stamp could then belong to either frame, so neither is checked.
            key = _stamp_key(frame[specs[0].topic]) if typed else None
            ambiguous = key is not None and key in used_keys
            used_keys.update(_stamp_key(m) for m in frame.values() if not isinstance(m, bytes))
            for t, w in outs.items():
                if ambiguous:
                    w.drop_check(key)
                    continue
                chk = invariant(name, t, frame) if typed else None
                if chk is not None:
                    w.add_check(key, chk)
            n_ambiguous += ambiguous
            t_case = time.monotonic()
            for topic, msg in case.messages:
                pubs[topic].publish(msg)
            sent_msgs += len(case.messages)
            malformed += case.malformed
            # rmw drops corrupt bytes for typed subscriptions: they never arrive
            after, lost, ok = settle(node, counters, before, len(case.messages), heavy, state,
                                     recv_timeout=2.0 if typed else 0.5)
            unsettled += not ok
            c = cats[case.category]
            if not ok:
                c["unsettled"] = c.get("unsettled", 0) + 1
            dt = time.monotonic() - t_case
            c["cases"] += 1
            c["malformed_messages"] += case.malformed
            c["seconds"] = round(c["seconds"] + dt, 3)
            c["max_case_s"] = round(max(c["max_case_s"], dt), 3)
            o = c["outcomes"]
            refused_before = o["dropped.undecodable_input"]
            late_refused = 0
            o["processed"] += after["frames_out"] - before["frames_out"]
            for k in after:
                if k.startswith("dropped."):
                    n = after[k] - before.get(k, 0)
                    if k == "dropped.undecodable_input":
                        # corrupt bytes of an earlier case are refused now: their refusal
                        # is theirs, not this case's
                        while corrupt_pending and (
                                case.index - corrupt_pending[0][0] > LATE_REFUSAL_CASES):
                            corrupt_pending.popleft()
                        late = 0
                        while corrupt_pending and late < n:
                            i, m = corrupt_pending.popleft()
                            take = min(m, n - late)
                            late += take
                            if m > take:
                                corrupt_pending.appendleft((i, m - take))
                        late_refused = late
                        cats["corrupt_cdr"]["outcomes"][k] += late
                        cats["corrupt_cdr"]["outcomes"]["refused_late"] += late
                        n -= late
                    o[k] += n
            if case.category == "corrupt_cdr":
                # the refusals still to come of this case's corrupt messages
                due = (sum(isinstance(m, bytes) for _, m in case.messages)
                       - (o["dropped.undecodable_input"] - refused_before - late_refused))
                if due > 0:
                    corrupt_pending.append((case.index, due))
            o["sync.late"] += after["late"] - before["late"]
            o["sync.discarded"] += after["sync_dropped"] - before["sync_dropped"]
            o["sync.resets"] += after["resets"] - before["resets"]
            o["lost_in_transport"] += lost
            if after.get("dropped.processing_error", 0) > before.get("dropped.processing_error", 0):
                errs = [m for m in node.diag.status().message.split("; ")
                        if m.startswith("processing error")]
                if len(c["examples"]) < 5 and errs:
                    c["examples"].setdefault(case.variant[:60], errs[0][:300])
            if case.category != "corrupt_cdr" and o["dropped.undecodable_input"] > refused_before:
                # a valid message refused: what the node said, to find the decoder's bug
                said = [m for m in node.diag.status().message.split("; ")
                        if any(t in m for t in REFUSALS)]
                c.setdefault("refused", []).append(
                    {"variant": case.variant[:60], "previous": prev_category,
                     "said": said[:3]})
            prev_category = case.category
            if (case.index + 1) % 1000 == 0:
                print(f"  {name}: {case.index + 1}/{cases} cases, "
                      f"{time.monotonic() - t_fuzz:.0f} s", flush=True)
        report["fuzz_s"] = round(time.monotonic() - t_fuzz, 1)
        report["messages_sent"] = sent_msgs
        report["malformed_messages"] = malformed
        report["unsettled_cases"] = unsettled
        report["categories"] = {k: {**v, "outcomes": {a: b for a, b in v["outcomes"].items() if b}}
                                for k, v in sorted(cats.items())}

        # valid frames after the garbage
        time.sleep(0.5)  # outputs of the last cases still in flight reach their checks
        checks = []
        stamp = fuzzer.next_stamp_ns()
        for attempt in range(2):
            frame, got = send_valid(stamp + attempt * 100_000_000)
            diffs = {t: "no output" if m is None else difference(ref[t], m)
                     for t, m in got.items()}
            entry = {"stamp_ns": stamp + attempt * 100_000_000,
                     "outputs": {t: m is not None for t, m in got.items()},
                     "differences_from_reference": {t: d for t, d in diffs.items() if d}}
            entry["processed"] = all(entry["outputs"].values())
            entry["correct"] = entry["processed"] and not entry["differences_from_reference"]
            checks.append(entry)
        time.sleep(0.3)
        report["valid_frames_after"] = checks
        report["invariants"] = {
            "checked": sum(w.checked for w in outs.values()),
            "skipped_repeated_stamps": n_ambiguous,
            "violations": sum(w.n_violations for w in outs.values()),
            "examples": [v for w in outs.values() for v in w.violations][:10]}
        report["executor_errors"] = [e[-1500:] for e in ros.errors[:5]]
        report["n_executor_errors"] = len(ros.errors)
        ros.errors.clear()  # reported here; close() would raise on them
        worker_alive = node.inputs.worker._thread.is_alive()
        report["alive"] = bool(worker_alive and report["n_executor_errors"] == 0
                               and checks[0]["processed"])
        report["diagnostics"] = {v.key: v.value for v in node.diag.status().values}
        # node and harness share this process: its peak RSS bounds the node's
        report["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        # an exception contained by the frame worker is no clear refusal of bad input
        report["processing_errors"] = sum(c["outcomes"].get("dropped.processing_error", 0)
                                          for c in report["categories"].values())
        # every message but corrupt_cdr's is valid CDR (rclpy made it): a raw decoder
        # refusing one is a decoder bug
        report["valid_cdr_refused"] = sum(
            c["outcomes"].get("dropped.undecodable_input", 0)
            for k, c in report["categories"].items() if k != "corrupt_cdr")
        report["passed"] = bool(report["alive"] and checks[0]["correct"]
                                and report["invariants"]["violations"] == 0
                                and report["processing_errors"] == 0
                                and report["valid_cdr_refused"] == 0)
        return report
    except Exception as exc:  # noqa: BLE001 - the report says what went wrong
        import traceback
        report["error"] = f"{type(exc).__name__}: {exc}"
        report["traceback"] = traceback.format_exc()[-3000:]
        report["passed"] = False
        return report
    finally:
        report["elapsed_s"] = round(time.monotonic() - t_start, 1)
        ros.errors.clear()
        ros.close()


# ---------------------------------------------------------------------------- report
def _row(outcomes: dict) -> dict:
    own = sum(v for k, v in outcomes.items() if k.startswith("dropped."))
    return {"processed": outcomes.get("processed", 0), "dropped": own,
            "sync": outcomes.get("sync.late", 0) + outcomes.get("sync.discarded", 0),
            "errors": outcomes.get("dropped.processing_error", 0),
            "lost": outcomes.get("lost_in_transport", 0)}


LEGEND = """columns: frames = malformed frames sent, malformed = malformed messages in them;
then what the node's counters did while each frame was handled: processed / dropped =
frames processed / dropped with a reason (reasons in the JSON), proc.err = dropped by an
exception the frame worker contained, sync = messages the synchroniser discarded (late,
unmatched, overflow), lost = messages never received (rmw drops bytes it cannot
deserialize for a typed subscription); max s = slowest frame."""


def print_table(report: dict) -> None:
    print("\n" + LEGEND)
    for name, r in report["nodes"].items():
        print(f"\n== {name}: ", end="")
        if not r.get("started"):
            print(f"did not start: {r.get('start_errors') or r.get('error')}")
            continue
        if "categories" not in r:
            print(f"failed: {r.get('error')}")
            continue
        frames = sum(c["cases"] for c in r["categories"].values())
        print(f"{r['malformed_messages']} malformed messages in {frames} frames "
              f"({r['messages_sent']} messages) on {', '.join(r['inputs'])}; {r['fuzz_s']} s")
        print(f"{'category':26s} {'frames':>7s} {'malformed':>9s} {'processed':>9s} "
              f"{'dropped':>8s} {'proc.err':>8s} {'sync':>6s} {'lost':>5s} {'max s':>6s}")
        for cat, c in r["categories"].items():
            x = _row(c["outcomes"])
            print(f"{cat:26s} {c['cases']:7d} {c['malformed_messages']:9d} {x['processed']:9d} "
                  f"{x['dropped']:8d} {x['errors']:8d} {x['sync']:6d} {x['lost']:5d} "
                  f"{c['max_case_s']:6.2f}")
        v = r["valid_frames_after"][0]
        print(f"alive: {r['alive']}  executor errors: {r['n_executor_errors']}  "
              f"processing errors: {r['processing_errors']}  "
              f"valid CDR refused: {r['valid_cdr_refused']}  "
              f"valid frame after: processed={v['processed']} equal to reference={v['correct']}  "
              f"invariant checks: {r['invariants']['checked']} "
              f"({r['invariants']['violations']} violations)  peak RSS {r['peak_rss_mb']} MB"
              f"  -> {'PASS' if r['passed'] else 'FAIL'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", default=",".join(NODES), help=f"subset of {', '.join(NODES)}")
    ap.add_argument("--cases", type=int, default=10_000, help="malformed frames per node")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--huge-clouds", type=int, default=3, help="2-million-point clouds per node")
    ap.add_argument("--box-floods", type=int, default=None,
                    help="arrays of thousands of boxes per node (default: cases / 500)")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="extra node parameter (YAML value), e.g. lmd.classifier_path=/x.joblib")
    ap.add_argument("--out", default=str(ROOT / "out" / "fuzz" / "report.json"))
    ap.add_argument("--update", action="store_true",
                    help="keep the other nodes of an existing --out report (rerun some nodes)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    import yaml
    extra: dict[str, dict] = defaultdict(dict)
    for p in args.param:
        key, _, value = p.partition("=")
        node, _, pname = key.partition(".")
        extra[node][pname] = yaml.safe_load(value)

    if args.child:  # one node, report to --out
        r = fuzz_node(args.child, args.cases, args.seed, extra, args.huge_clouds, args.box_floods)
        Path(args.out).write_text(json.dumps(r, indent=1, default=str))
        return 0

    names = [n.strip() for n in args.nodes.split(",") if n.strip()]
    unknown = set(names) - set(NODES)
    if unknown:
        ap.error(f"unknown node(s) {sorted(unknown)}; known: {', '.join(NODES)}")
    report = {"cases_per_node": args.cases, "seed": args.seed, "nodes": {}}
    if args.update and Path(args.out).exists():
        report["nodes"] = json.loads(Path(args.out).read_text())["nodes"]
    for name in names:
        print(f"fuzzing {name}: {args.cases} malformed frames (seed {args.seed})", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            part = Path(tmp) / f"{name}.json"
            cmd = [sys.executable, str(Path(__file__).resolve()), "--child", name,
                   "--cases", str(args.cases), "--seed", str(args.seed),
                   "--huge-clouds", str(args.huge_clouds), "--out", str(part)]
            if args.box_floods is not None:
                cmd += ["--box-floods", str(args.box_floods)]
            for p in args.param:
                cmd += ["--param", p]
            log = Path(args.out).with_name(f"{name}_node.log")
            log.parent.mkdir(parents=True, exist_ok=True)
            with open(log, "w") as fh:
                proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT,
                                      env={**os.environ, "PYTHONFAULTHANDLER": "1"})
            if part.exists():
                r = json.loads(part.read_text())
            else:
                r = {"node": name, "started": False, "passed": False,
                     "error": f"fuzz process died with exit code {proc.returncode} (log: {log})"}
            r["process_exit_code"] = proc.returncode
            report["nodes"][name] = r
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=str) + "\n")
    print_table(report)
    print(f"\nwrote {out}")
    return 0 if all(r.get("passed") for r in report["nodes"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
