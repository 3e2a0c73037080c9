"""``process_bag``: the three quality nodes over recorded perception bags, offline (no DDS).

    process_bag --bag IN [--bag IN2 ...] --out OUT [--nodes lmd,lms,mimo] [--results DIR]
                [--topic points=/sensing/lidar/top/pointcloud ...]
                [--param lmd.proposal_mode=exact ...] [--overwrite] [--no-progress]

IN is a bag or a folder of bags (``perception_bag.resolve_bags``), any rosbag2 that ``ros2
bag`` reads (``bag_io``: sqlite3 or MCAP, older metadata). A single bag gives the output bag
OUT; several (or a folder) give OUT/<input name> each, every bag a stream of its own (the
processors' intensity decision, beam table and drift window start afresh). The output bag (MCAP) holds every
input message unchanged (topic, type, log time, recorded QoS; types unknown here, e.g. a
driver's raw packets, copied as bytes with one warning per type) plus what the nodes publish
for each frame, at the log time of the frame's cloud: ``/lmd/output/{detections,
quality}``, ``/lms/output/{points,segments}``, ``/mimo/output/{detections,uncertainty}``.
The input topics are the nodes' inputs under the reference perception's names
(``/lidar/points``, ``/perception/detections`` ...); ``--topic KEY=TOPIC`` names another
(keys: the nodes' input names without ``input/``: points, detections, proposals,
segmentation, head_0, head_0/variance ...). Each output bag is written in a hidden folder
beside it and moved into place when complete: a failed or interrupted run leaves no output
bag (and needs no ``--overwrite`` the next time); ``--overwrite`` replaces a complete one.

Settings are the nodes': the installed ``config/<node>_node.yaml`` with ``--param
node.name=value`` overrides (YAML values), mapped to the pipelines' settings and models
as the nodes map them; the frame work is the nodes' processors (``LmdProcessor``,
``LmsProcessor``, ``mimo_ros.pipeline.MimoProcessor``), detection arrays decoded from
their bytes (``detection_cdr``) as the nodes do. Inputs are grouped by header stamp; a
frame is processed once it has all input topics of the bag, or when 16 newer stamps have
come. A frame a node cannot process (missing input, undecodable or malformed message,
an exception) is dropped for that node and counted by reason, never the run. Exit codes:
0 done; 1 a node processed no frame of a bag (why on stderr: its topics are not in the
bag, or every frame was dropped, with the reasons counted; the output bags are written
all the same), or a bag could not be read (no output for it); 2 bad arguments, parameters
or models (nothing written); 130 interrupted (the bag in progress not written).
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from lidar_quality_core.frame import FrameRejected
from lidar_quality_core.time_sync import stamp_of_bytes
from lidar_quality_ros.perception_bag import (add_topic_option, parse_topic_options,
                                              resolve_bags, topic_of)

NODES = {"lmd": "lmd_ros", "lms": "lms_ros", "mimo": "mimo_ros"}
DET, QUAL = "vision_msgs/msg/Detection3DArray", "lidar_quality_msgs/msg/"
OUTPUTS = {"lmd": (("/lmd/output/detections", DET),
                   ("/lmd/output/quality", QUAL + "DetectionQualityArray")),
           "lms": (("/lms/output/points", "sensor_msgs/msg/PointCloud2"),
                   ("/lms/output/segments", QUAL + "SegmentQualityArray")),
           "mimo": (("/mimo/output/detections", DET),
                    ("/mimo/output/uncertainty", QUAL + "ClusterUncertaintyArray"))}
WINDOW = 16        # newer stamps after which an incomplete frame is processed as it is
MAX_WARNINGS = 3   # per node and reason; the summary counts them all


class UsageError(ValueError):
    """A bad argument, parameter or model: nothing is processed."""


class Drop(Exception):
    """A frame a node does not process, with the reason counted in the summary."""

    def __init__(self, reason: str, text: str = ""):
        super().__init__(text or reason)
        self.reason = reason


# ----------------------------------------------------------------------- parameters
def parameters_class(node: str):
    """The dataclass declaring ``node``'s own parameters (besides the common ones)."""
    if node == "lmd":
        from lmd_ros.pipeline import LmdParameters as cls
    elif node == "lms":
        from lms_ros.pipeline import LmsParameters as cls
    else:
        from mimo_ros.pipeline import MimoParameters as cls
    return cls


def node_specs(node: str) -> dict:
    """Every parameter ``node`` declares, by name (the node's own declarations)."""
    from lidar_quality_core.parameters import parameter_specs
    from lidar_quality_ros.node_base import BASE_PARAMETERS

    return {s.name: s for s in BASE_PARAMETERS + parameter_specs(parameters_class(node))}


def node_parameters(node: str, overrides: dict | None = None) -> dict:
    """The node's parameter values: declared defaults, then its installed config YAML, then
    ``overrides``; every value checked as the node checks it (unknown names, another type
    or a value outside the declared range / choices raise ``UsageError``)."""
    from lidar_quality_ros.params import config_parameters

    specs = node_specs(node)
    params = {name: spec.default for name, spec in specs.items()}
    config = config_parameters(NODES[node], f"{node}_node")
    for source, values in (("config", config), ("override", overrides or {})):
        for name, value in values.items():
            if name not in specs:
                raise UsageError(f"unknown parameter {node}.{name} ({source}; known: "
                                 f"{', '.join(specs)})")
            default = specs[name].default
            if isinstance(default, float) and type(value) is int:
                value = float(value)
            elif isinstance(default, str) and not isinstance(value, str) and value is not None:
                value = str(value)      # e.g. ring_field=on: YAML's bool, meant as a name
            if type(value) is not type(default):
                raise UsageError(f"parameter {node}.{name} = {value!r}: expected a "
                                 f"{type(default).__name__} like {default!r}")
            try:
                specs[name].check(value)
            except ValueError as exc:
                raise UsageError(f"{node}: {exc}") from None
            params[name] = value
    return params


def node_config(node: str, params: dict):
    """The node's parameters object (``parameters_class``) of ``params``, its settings
    validated as the node validates them."""
    from lidar_quality_core.parameters import from_parameters, validate

    config = from_parameters(parameters_class(node), params)
    validate(config)
    return config


def node_settings(node: str, params: dict):
    """The pipeline settings a node builds from its parameters (``node_parameters``)."""
    return node_config(node, params).settings


def _models(node: str, config):
    import importlib

    pipeline = importlib.import_module(f"{NODES[node]}.pipeline")
    try:
        return pipeline.load_models(config, warn=lambda t: print(
            f"process_bag: {node}: warning: {t}", file=sys.stderr))
    except RuntimeError as exc:  # any load failure refuses the run
        raise UsageError(f"{node}: {exc}") from exc


# ----------------------------------------------------------------------- node runners
@dataclass
class Runner:
    """One node: its input topics (key -> topic), which of them it needs, and ``run``
    (``get(key)`` -> decoded message or None) -> the processor's frame outputs
    (``lidar_quality_core.frame``)."""

    name: str
    topics: dict
    required: tuple
    run: Callable
    processor: object = None  # its ``transforms`` are set per bag (/tf_static, /tf)

    def model_ids(self) -> dict:
        """``{"confidence": id, "iou": id}`` of the processor's meta models."""
        models = getattr(self.processor, "models", None)
        return {"confidence": getattr(models, "confidence_model_id", ""),
                "iou": getattr(models, "iou_model_id", "")}


def _lmd(p: dict, topics: dict) -> Runner:
    from lmd_ros.pipeline import LmdProcessor

    c = node_config("lmd", p)
    from lidar_quality_core.thresholds import from_parameters as thresholds_from

    proc = LmdProcessor(c.settings, _models("lmd", c), min_confidence=c.min_confidence,
                        transform_inputs=c.transform_inputs,
                        transform_tolerance=c.transform_tolerance,
                        thresholds=thresholds_from(c.min_confidence, c.class_min_confidence,
                                                   c.range_min_confidence), drift=c.drift)
    mode = c.settings.proposal_mode
    keys = ["points"] + (["detections"] if mode != "exact" else []) + (
        ["proposals"] if mode != "none" else [])
    return Runner("lmd", {k: topic_of(k, topics) for k in keys}, tuple(keys),
                  lambda get: proc.process(get("points"), get("detections"), get("proposals")),
                  processor=proc)


def _lms(p: dict, topics: dict) -> Runner:
    from lms_ros.pipeline import LmsProcessor

    c = node_config("lms", p)
    proc = LmsProcessor(c.settings, _models("lms", c), all_fields=c.output_all_fields,
                        drift=c.drift)
    # the segmentation cloud carries points and probabilities; separately: /lidar/points
    keys = ("points", "segmentation") if c.separate_probabilities else ("segmentation",)
    return Runner("lms", {k: topic_of(k, topics) for k in keys}, keys,
                  lambda get: proc.process(get(keys[0]),
                                           get("segmentation") if len(keys) == 2 else None),
                  processor=proc)


def _mimo(p: dict, names: dict) -> Runner:
    from mimo_ros.pipeline import MimoProcessor, NoHeadError

    c = node_config("mimo", p)
    s = c.settings
    from lidar_quality_core.thresholds import from_parameters as thresholds_from

    proc = MimoProcessor(s, _models("mimo", c), scores=c.output_scores,
                         transform_inputs=c.transform_inputs,
                         transform_tolerance=c.transform_tolerance,
                         thresholds=thresholds_from(c.min_confidence, c.class_min_confidence,
                                                    c.range_min_confidence), drift=c.drift)
    K = s.num_heads
    topics = {f"head_{k}": topic_of(f"head_{k}", names) for k in range(K)}
    if c.use_variances:
        topics.update({f"var_{k}": topic_of(f"head_{k}/variance", names) for k in range(K)})
    if s.use_points:
        topics["points"] = topic_of("points", names)

    def run(get):
        undecodable = {}

        def optional(key):  # as the node: a bad message is left out, the rest merged
            try:
                return get(key)
            except Drop as exc:
                undecodable["undecodable"] = str(exc)
                return None

        heads = [optional(f"head_{k}") for k in range(K)]
        variances = [optional(f"var_{k}") for k in range(K)] if c.use_variances else None
        cloud = optional("points") if s.use_points else None
        try:
            out = proc.process(heads, variances, cloud)
        except NoHeadError as exc:
            raise Drop("undecodable_input" if undecodable else exc.reason,
                       undecodable.get("undecodable", str(exc))) from None
        out.issues.update(undecodable)
        return out

    return Runner("mimo", topics, (), run, processor=proc)


def nodes_parameters(nodes, params: dict | None = None) -> dict:
    """node -> its full parameter values (``node_parameters``) for each of ``nodes``, with
    ``params`` (``{"lmd.name": value}`` or ``{"lmd": {"name": value}}``) applied; bad names
    and parameters of nodes not in ``nodes`` raise ``UsageError``."""
    unknown = [n for n in nodes if n not in NODES]
    if unknown or not nodes:
        raise UsageError(f"unknown node(s) {unknown or '(none given)'}: choose from "
                         f"{', '.join(NODES)}")
    per_node: dict = {n: {} for n in NODES}
    for key, value in (params or {}).items():
        node, _, name = key.partition(".")
        if node not in NODES or not (name or isinstance(value, dict)):
            raise UsageError(f"parameter {key!r}: expected <node>.<name> with node one of "
                             f"{', '.join(NODES)}")
        per_node[node].update(value if not name else {name: value})
    for node, over in per_node.items():
        if over and node not in nodes:
            raise UsageError(f"parameters given for {node}, which is not in --nodes")
    return {n: node_parameters(n, per_node[n]) for n in nodes}


def build_runners(nodes=tuple(NODES), params: dict | None = None,
                  topics: dict | None = None) -> list[Runner]:
    """Runners of ``nodes`` with their settings and models; ``params``: ``{"lmd.name":
    value}`` or ``{"lmd": {"name": value}}``; ``topics``: input key -> bag topic (``--topic``,
    unnamed keys keep the default names). Raises ``UsageError`` for anything bad."""
    try:
        topics = parse_topic_options([f"{k}={v}" for k, v in (topics or {}).items()])
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    make = {"lmd": _lmd, "lms": _lms, "mimo": _mimo}
    runners = []
    for n, values in nodes_parameters(nodes, params).items():
        try:
            runners.append(make[n](values, topics))
        except UsageError:
            raise
        except (ValueError, TypeError) as exc:  # settings' validation, MergeConfig
            raise UsageError(f"invalid {n} parameter: {exc}") from exc
    return runners


# ----------------------------------------------------------------------- one bag
@dataclass
class _Frame:
    stamp_ns: int
    points_topic: str
    msgs: dict = field(default_factory=dict)   # topic -> BagMessage
    decoded: dict = field(default_factory=dict)

    def log_ns(self) -> int:
        cloud = self.msgs.get(self.points_topic)
        return cloud.stamp_ns if cloud else min(m.stamp_ns for m in self.msgs.values())

    def get(self, topic: str):
        """The decoded message (``None`` where absent); ``Drop`` when it cannot be."""
        if topic not in self.decoded:
            m = self.msgs.get(topic)
            try:
                if m is None:
                    value = None
                elif m.msgtype == DET:
                    from lidar_quality_core.detection_cdr import decode_detection_array
                    value = decode_detection_array(m.raw)
                else:
                    value = m.decode()
            except Exception as exc:  # noqa: BLE001 - rclpy raises RuntimeError subclasses
                value = Drop("undecodable_input", f"cannot decode {topic}: {exc}")
            self.decoded[topic] = value
        value = self.decoded[topic]
        if isinstance(value, Drop):
            raise value
        return value


@dataclass
class NodeStats:
    frames_in: int = 0
    frames_out: int = 0
    dropped: Counter = field(default_factory=Counter)
    counts: Counter = field(default_factory=Counter)
    issues: Counter = field(default_factory=Counter)   # frames with an input problem, by key
    wall_s: float = 0.0
    absent_topics: list = field(default_factory=list)  # input topics not in the bag
    values: dict = field(default_factory=dict)          # the last frame's values

    def summary(self) -> dict:
        return {"frames_in": self.frames_in, "frames_out": self.frames_out,
                "absent_topics": list(self.absent_topics),
                "frames_dropped": sum(self.dropped.values()), "dropped": dict(self.dropped),
                "counts": dict(self.counts), "issues": dict(self.issues),
                "values": dict(self.values),
                "wall_s": round(self.wall_s, 3),
                "frames_per_s": round(self.frames_in / self.wall_s, 2) if self.wall_s else None}


class _Warnings:
    """stderr warnings, at most ``MAX_WARNINGS`` per node and reason."""

    def __init__(self, bag: str, progress: bool):
        self.bag, self.seen, self.nl = bag, Counter(), "\n" if progress else ""

    def __call__(self, node: str, reason: str, text: str) -> None:
        self.seen[node, reason] += 1
        n = self.seen[node, reason]
        if n <= MAX_WARNINGS:
            more = f" (further '{reason}' warnings not shown)" if n == MAX_WARNINGS else ""
            sys.stderr.write(f"{self.nl}{self.bag}: {node}: {text}{more}\n")


def _process_frame(frame: _Frame, runners, stats, warn, write, collect=None) -> None:
    log_ns = frame.log_ns()
    for r in runners:
        if not any(t in frame.msgs for t in r.topics.values()):
            continue           # not this node's frame
        st = stats[r.name]
        st.frames_in += 1
        t0 = time.perf_counter()
        try:
            missing = [r.topics[k] for k in r.required if r.topics[k] not in frame.msgs]
            if missing:
                raise Drop("missing_input", f"no {', '.join(missing)} at stamp {frame.stamp_ns}")
            out = r.run(lambda key: frame.get(r.topics[key]) if key in r.topics else None)
        except Drop as exc:
            st.dropped[exc.reason] += 1
            warn(r.name, exc.reason, f"frame at stamp {frame.stamp_ns} dropped: {exc}")
            continue
        except Exception as exc:  # noqa: BLE001 - FrameRejected, ValueError, bugs: reported
            # as the node: a rejected frame counts under its reason
            reason = exc.reason if isinstance(exc, FrameRejected) else "processing_error"
            st.dropped[reason] += 1
            warn(r.name, reason, f"frame at stamp {frame.stamp_ns} dropped: "
                                 f"{type(exc).__name__}: {exc}")
            continue
        finally:
            st.wall_s += time.perf_counter() - t0
        st.frames_out += 1
        st.counts.update(out.counts)
        for key, text in out.issues.items():
            st.issues[key] += 1
            warn(r.name, key, f"stamp {frame.stamp_ns}: {text}")
        for text in out.notes:   # decisions (e.g. intensity_scale: auto)
            warn(r.name, "note", text)
        st.values.update(out.values)
        if collect is not None:
            collect(r.name, frame, out)
        for (topic, msgtype), msg in zip(OUTPUTS[r.name], out.messages.values()):
            write(topic, msgtype, log_ns, msg)


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise UsageError(f"{out} exists: pass --overwrite or choose another --out")
        if not ((out / "metadata.yaml").exists() or (out.is_dir() and not any(out.iterdir()))):
            raise UsageError(f"{out} exists and is not a bag: not overwriting it")


def _run(in_bag: Path, out_bag: Path | None, runners, *, progress: bool, window=None,
         collect=None, on_frame=None, extra_topics=()) -> dict:
    """Process ``in_bag`` into ``out_bag`` (replaced if it exists, only once complete; None:
    no output bag). ``window``: ``(start_ns, stop_ns)``, only the frames whose cloud is
    logged in it (a slice of a long bag; the transforms from before it still apply);
    ``collect(node, frame, outputs)`` sees every processed frame (``fleet.ResultRows``),
    ``on_frame()`` is called after each frame; ``extra_topics`` (e.g. ground truth for
    ``collect``) are grouped into the frames too where the bag has them."""
    from lidar_quality_core.progress import Progress
    from lidar_quality_ros.bag_io import UnknownTypes, atomic_output, bag_info

    t_start = time.perf_counter()
    info = bag_info(in_bag)
    warn = _Warnings(in_bag.name, progress)
    for fix in info.fixes:
        warn("bag", "metadata", f"note: metadata read with a correction: {fix}")
    unknown = UnknownTypes(lambda text: warn("bag", "unknown_type", text),
                           "copied to the output unchanged, not decoded")
    known = set(unknown.check_all({t: i.msgtype for t, i in info.topics.items()}))
    wanted = {t for r in runners for t in r.topics.values() if t in known}
    wanted |= {t for t in extra_topics if t in known}
    stats = {r.name: NodeStats() for r in runners}
    for r in runners:
        absent = [t for t in r.topics.values() if t not in known]
        if absent:
            stats[r.name].absent_topics = absent
            undecodable = [t for t in absent if t in info.topics]
            warn(r.name, "absent_topics", f"topics not in the bag: {', '.join(absent)}" + (
                f" ({', '.join(undecodable)}: type not available here)" if undecodable else ""))
    bar = Progress(f"{in_bag.name}", max((info.topics[t].count for t in wanted), default=0),
                   enabled=progress and window is None)
    step = bar.update if on_frame is None else (lambda: (bar.update(), on_frame()))
    try:
        if out_bag is None:
            n_frames, copied, late = _write(in_bag, None, runners, info, wanted, stats, warn,
                                            step, window, collect)
        else:
            with atomic_output(out_bag, overwrite=True) as tmp:
                n_frames, copied, late = _write(in_bag, tmp, runners, info, wanted, stats,
                                                warn, step, window, collect)
    finally:
        bar.close()
    nodes = {name: st.summary() for name, st in stats.items()}
    return {"in": str(in_bag), "out": str(out_bag) if out_bag else None, "frames": n_frames,
            "window": list(window) if window else None, "messages_copied": copied,
            "messages_not_processed": dict(late),
            "unknown_types": {ty: list(ts) for ty, ts in unknown.seen.items()},
            "metadata_fixes": list(info.fixes),
            "wall_s": round(time.perf_counter() - t_start, 3), "nodes": nodes,
            "no_output": no_output_reasons(nodes, sorted(info.topics), dict(late))}


def new_streams(runners) -> None:
    """Every processor forgets its stream (intensity decision, drift window, ...)."""
    for r in runners:
        getattr(r.processor, "new_stream", lambda: None)()


def _transform_feed(runners, warn) -> Callable:
    """Fresh transform buffers for this bag's processors that transform their inputs, and
    ``feed(message)``: /tf_static and /tf (tf2_msgs/msg/TFMessage) go into them, as the
    nodes' TfListener does."""
    from lidar_quality_core.transforms import TransformBuffer, add_tf_message

    procs = [r.processor for r in runners if getattr(r.processor, "transform_inputs", False)]
    for proc in procs:
        proc.transforms = TransformBuffer(extrapolation_tolerance_s=proc.transform_tolerance)

    def feed(m) -> None:
        if not procs or m.topic not in ("/tf_static", "/tf") or \
                m.msgtype != "tf2_msgs/msg/TFMessage":
            return
        try:
            msg = m.decode()
        except Exception as exc:  # noqa: BLE001 - rclpy raises RuntimeError subclasses
            warn("bag", "tf", f"{m.topic} message not decoded: {exc}")
            return
        for proc in procs:
            bad = add_tf_message(proc.transforms, msg, m.topic == "/tf_static")
        if bad:
            warn("bag", "tf", f"{m.topic}: {len(bad)} transform(s) refused: {bad[0]}")

    return feed


class _NoBag:
    """The writer when no output bag is asked for."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def write(self, *args, **kwargs) -> None:
        return None


#: a slice reads this much of the bag before and after its window: frames whose messages
#: straddle the boundary are complete in the slice their cloud belongs to
SLICE_MARGIN_NS = 2_000_000_000


def _slice_messages(in_bag: Path, window, feed_tf):
    """The messages of ``window`` plus ``SLICE_MARGIN_NS`` either side; the transforms
    logged before that fed first (/tf_static is recorded once, at the bag's start)."""
    from lidar_quality_ros.bag_io import read_bag

    start = window[0] - SLICE_MARGIN_NS
    for m in read_bag(in_bag, {"/tf_static", "/tf"}, stop_ns=max(start, 0)):
        feed_tf(m)
    yield from read_bag(in_bag, start_ns=max(start, 0), stop_ns=window[1] + SLICE_MARGIN_NS)


def _write(in_bag: Path, out_bag: Path | None, runners, info, wanted, stats, warn, step,
           window=None, collect=None):
    from lidar_quality_ros.bag_io import BagWriter, read_bag
    from lidar_quality_ros.qos import output_qos

    points_topic = next((r.topics["points"] for r in runners if "points" in r.topics),
                        topic_of("points"))
    pending: dict[int, _Frame] = {}
    backlog: list = []                 # input messages read, not yet written (log order)
    last_done, late, copied, n_frames = None, Counter(), 0, 0
    feed_tf = _transform_feed(runners, warn)
    lo, hi = window if window else (-1, float("inf"))
    with BagWriter(out_bag) if out_bag is not None else _NoBag() as w:
        def write(topic, msgtype, log_ns, msg):
            qos = [output_qos(5 if topic == "/lms/output/points" else 10)]
            w.write(topic, msgtype, log_ns, msg, qos=qos)

        def drain(upto: float) -> None:   # copy input messages logged up to ``upto``
            nonlocal copied
            k = 0
            n = 0
            while k < len(backlog) and backlog[k].stamp_ns <= upto:
                m = backlog[k]
                k += 1
                if not lo <= m.stamp_ns < hi:
                    continue       # another slice's
                t = info.topics[m.topic]
                w.write(m.topic, m.msgtype, m.stamp_ns, m.raw, qos=t.qos, source=t)
                n += 1
            copied += n
            del backlog[:k]

        def flush(keep: int) -> None:  # oldest frames: complete ones, or beyond ``keep``
            nonlocal last_done, n_frames
            while pending:
                oldest = min(pending)
                f = pending[oldest]
                if len(pending) <= keep and not wanted <= f.msgs.keys():
                    break
                del pending[oldest]
                drain(f.log_ns())
                last_done = oldest
                if not lo <= f.log_ns() < hi:
                    continue       # another slice's frame
                _process_frame(f, runners, stats, warn, write, collect)
                n_frames += 1
                step()

        messages = _slice_messages(in_bag, window, feed_tf) if window else read_bag(in_bag)
        for m in messages:
            backlog.append(m)
            feed_tf(m)
            if m.topic in wanted:
                try:
                    stamp = stamp_of_bytes(m.raw)
                except ValueError as exc:
                    stamp = exc
                if isinstance(stamp, Exception) or (last_done is not None and stamp <= last_done):
                    why = "unreadable_stamp" if isinstance(stamp, Exception) else "late"
                    if lo <= m.stamp_ns < hi:   # a margin's message is another slice's
                        late[why] += 1
                        for r in runners:
                            if m.topic in r.topics.values():
                                warn(r.name, why, f"{m.topic} message at log time "
                                                  f"{m.stamp_ns} not processed ({why}): "
                                                  "copied only")
                else:
                    pending.setdefault(stamp, _Frame(stamp, points_topic)).msgs[m.topic] = m
                    flush(WINDOW)
            if not pending:
                drain(float("inf"))
        flush(0)
        drain(float("inf"))
    return n_frames, copied, late


def no_output_reasons(nodes: dict, bag_topics: list, not_processed: dict | None = None) -> dict:
    """node -> why it processed no frame of the bag (nodes with an output are left out):
    its topics are not in the bag, or every frame was dropped (the reasons counted)."""
    out = {}
    for name, n in nodes.items():
        if n["frames_out"]:
            continue
        absent = n.get("absent_topics") or []
        why = []
        if absent:
            why.append(f"{'its input topics are' if not n['frames_in'] else 'input topics'} "
                       f"not in the bag: {', '.join(absent)} (the bag has: "
                       f"{', '.join(bag_topics) or 'no topic'})")
        if n["dropped"]:
            why.append(f"every frame dropped ({n['frames_in']}): " + ", ".join(
                f"{k} {v}" for k, v in sorted(n["dropped"].items())))
        elif not absent:
            late = ", ".join(f"{k} {v}" for k, v in sorted((not_processed or {}).items()))
            why.append("no frame with its inputs" + (f" (messages not processed: {late})"
                                                     if late else ""))
        out[name] = "; ".join(why)
    return out


def process_one(in_bag: Path, out_bag: Path | None, runners, *, results: Path | None = None,
                part: str = "part-0000", name: str | None = None, topics: dict | None = None,
                window=None, progress: bool = False, on_frame=None, collect=None) -> dict:
    """One bag (or the slice ``window`` of it) into ``out_bag`` (None: no output bag) and,
    with ``results``, its result tables (``result_tables``) as
    ``results/<node>/bag=<name>/<part>.parquet``; the summary lists them (``"results"``).
    ``collect(node, frame, outputs)`` sees every processed frame as well."""
    from lidar_quality_ros.perception_bag import bag_group

    from .result_tables import ResultRows, write_table

    in_bag = Path(in_bag)
    rows = gt = None
    if results is not None:
        gt = {k: topic_of(k, topics) for k in ("gt_objects", "points_gt")}
        rows = ResultRows(runners, source=str(in_bag), group=bag_group(in_bag), gt_topics=gt,
                          warn=lambda text: print(f"process_bag: {in_bag.name}: warning: "
                                                  f"{text}", file=sys.stderr))
    if rows is not None and collect is not None:
        both = (rows.collect, collect)
        collect = lambda *a: [c(*a) for c in both]  # noqa: E731 - a two-line chain
    elif rows is not None:
        collect = rows.collect
    summary = _run(in_bag, out_bag, runners, progress=progress, window=window,
                   collect=collect, on_frame=on_frame,
                   extra_topics=tuple(gt.values()) if gt else ())
    files = {}
    summary["results_issues"] = dict(rows.issues) if rows is not None else {}
    if rows is not None:
        for node, table in rows.tables().items():
            path = Path(results) / node / f"bag={name or in_bag.name}" / f"{part}.parquet"
            files[node] = str(write_table(table, path))
    summary["results"] = files
    return summary


def process_bag(in_bag, out_bag, *, nodes=tuple(NODES), params: dict | None = None,
                topics: dict | None = None, progress: bool = True,
                overwrite: bool = False, results=None) -> dict:
    """Process one bag into ``out_bag``; returns the summary (JSON-able). ``topics``: input
    key -> bag topic (``--topic``); ``results``: a folder for the result tables
    (``process_one``). Bad arguments raise ``UsageError`` before anything is written."""
    in_bag, out_bag = Path(in_bag), Path(out_bag)
    nodes = nodes.split(",") if isinstance(nodes, str) else nodes
    if not (in_bag / "metadata.yaml").exists():
        raise UsageError(f"{in_bag}: not a rosbag2 directory")
    _plan([in_bag], out_bag)
    _check_out(out_bag, overwrite)
    return process_one(in_bag, out_bag, build_runners(tuple(nodes), params, topics),
                       results=results, topics=topics, progress=progress)


# ----------------------------------------------------------------------- command line
#: the processors' counts (``detections.in`` ...), with "." read as "_"
ITEMS = {"lmd": "{detections_in} det -> {detections_out}",
         "lms": "{points_in} pts, {segments} seg -> {segments_scored} scored",
         "mimo": "{boxes_in} boxes -> {detections_out} merged"}


class _Items(dict):
    """Counts for ``ITEMS``: ``detections_in`` reads ``detections.in``; absent: 0."""

    def __init__(self, counts):
        super().__init__({k.replace(".", "_"): v for k, v in counts.items()})

    def __missing__(self, key):
        return 0


def format_summary(summaries: list[dict]) -> str:
    """Per node, over all bags: frames in / out / dropped (reasons), items in / out, time."""
    total: dict[str, NodeStats] = {}
    for s in summaries:
        for name, n in s["nodes"].items():
            t = total.setdefault(name, NodeStats())
            t.frames_in += n["frames_in"]
            t.frames_out += n["frames_out"]
            t.dropped.update(n["dropped"])
            t.counts.update(n["counts"])
            t.wall_s += n["wall_s"]
    lines = [f"{'node':<6}{'in':>6}{'out':>6}{'dropped':>9}  {'items in -> out':<34}"
             f"{'wall s':>8}{'frames/s':>10}  drop reasons"]
    for name, t in total.items():
        fps = f"{t.frames_in / t.wall_s:.1f}" if t.wall_s else "-"
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(t.dropped.items())) or "-"
        lines.append(f"{name:<6}{t.frames_in:>6}{t.frames_out:>6}{sum(t.dropped.values()):>9}"
                     f"  {ITEMS[name].format_map(_Items(t.counts)):<34}{t.wall_s:>8.2f}{fps:>10}"
                     f"  {reasons}")
    wall = sum(s["wall_s"] for s in summaries)
    frames = sum(s["frames"] for s in summaries)
    lines.append(f"{len(summaries)} bag(s), {frames} frames, {wall:.2f} s wall in all "
                 f"({frames / max(wall, 1e-9):.1f} frames/s)")
    return "\n".join(lines)


def _parse_params(items) -> dict:
    import yaml

    out = {}
    for item in items:
        key, eq, text = item.partition("=")
        if not eq:
            raise UsageError(f"--param {item!r}: expected <node>.<name>=<value>")
        try:
            out[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise UsageError(f"--param {item!r}: not a YAML value: {exc}") from None
    return out


def _plan(bags, out: Path) -> list[tuple[Path, Path]]:
    """(input bag, output bag) pairs: OUT itself for one bag given as a bag, else OUT/<name>."""
    for b in map(Path, bags):
        if not b.exists():
            raise UsageError(f"--bag {b}: no such file or directory")
    try:
        inputs = resolve_bags(bags)
    except FileNotFoundError as exc:
        raise UsageError(str(exc)) from None
    single = len(bags) == 1 and inputs == [Path(bags[0])]
    pairs = [(b, out if single else out / b.name) for b in inputs]
    names = Counter(o for _, o in pairs)
    dup = [str(o) for o, n in names.items() if n > 1]
    if dup:
        raise UsageError(f"several input bags would write {', '.join(dup)}: give bags with "
                         "distinct names")
    for b, o in pairs:
        ri, ro = b.resolve(), o.resolve()
        if ri == ro or ri in ro.parents or ro in ri.parents:
            raise UsageError(f"output {o} overlaps input {b}")
    return pairs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="process_bag", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="exit codes: 0 done; 1 a node processed no frame of a "
                                 "bag (the reason on stderr; output bags written all the "
                                 "same); 2 bad arguments, parameters or models (nothing "
                                 "written)")
    ap.add_argument("--bag", action="append", required=True, metavar="IN",
                    help="input bag, or a folder of bags (repeatable)")
    ap.add_argument("--out", required=True, type=Path, help="output bag (one input bag) or "
                    "folder of output bags")
    ap.add_argument("--nodes", default=",".join(NODES), help="comma-separated subset of "
                    f"{','.join(NODES)} (default: all)")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="override a node parameter of its config YAML (repeatable)")
    add_topic_option(ap)
    ap.add_argument("--results", type=Path, metavar="DIR", help="also write the result "
                    "tables (Parquet, one row per scored detection / segment with its "
                    "features): DIR/<node>/bag=<name>/part-0000.parquet")
    ap.add_argument("--overwrite", action="store_true", help="replace existing (complete) "
                    "output bags")
    ap.add_argument("--no-progress", action="store_true", help="no progress line on stderr")
    args = ap.parse_args(argv)
    try:
        nodes = tuple(n.strip() for n in args.nodes.split(",") if n.strip())
        pairs = _plan(args.bag, args.out)
        if len(pairs) == 1 and pairs[0][1] == args.out:
            _check_out(args.out, args.overwrite)
        else:
            if args.out.exists() and not args.out.is_dir():
                raise UsageError(f"{args.out} is a file: --out must be a folder for several bags")
            for _, o in pairs:
                _check_out(o, args.overwrite)
        runners = build_runners(nodes, _parse_params(args.param), dict(args.topic))
    except UsageError as exc:
        ap.error(str(exc))
    summaries, unreadable = [], []
    for b, o in pairs:
        new_streams(runners)   # each bag from scratch, as a run of its own would
        try:
            summaries.append(process_one(b, o, runners, results=args.results,
                                         topics=dict(args.topic),
                                         progress=not args.no_progress))
        except KeyboardInterrupt:
            print(f"\nprocess_bag: interrupted: no output bag written for {b} (nor after it)",
                  file=sys.stderr)
            return 130
        except Exception as exc:  # noqa: BLE001 - a bag that cannot be read: said, not a traceback
            unreadable.append(b)
            print(f"process_bag: FAILED: cannot process {b}: {type(exc).__name__}: {exc} "
                  f"(no output bag written for it)", file=sys.stderr)
    if summaries:
        print(format_summary(summaries))
    failed = [(s["in"], node, why) for s in summaries for node, why in s["no_output"].items()]
    for bag, node, why in failed:
        print(f"process_bag: FAILED: {node} processed no frame of {bag}: {why}",
              file=sys.stderr)
    if failed:
        print(f"process_bag: exit 1: {len({n for _, n, _ in failed})} node(s) without output "
              f"(leave a node out with --nodes)", file=sys.stderr)
    return 1 if failed or unreadable else 0


if __name__ == "__main__":
    raise SystemExit(main())
