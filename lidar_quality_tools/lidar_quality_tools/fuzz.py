"""Seeded generator of malformed input messages for the quality nodes (issue 8, hardening).

A :class:`FrameTemplate` builds one valid input frame of a node (every input topic, one
stamp) from a ``lidar_quality_core.synthetic`` frame. A :class:`Fuzzer` turns it into a
deterministic stream of :class:`FuzzCase` s: each case is a complete frame in which one
message (for the timeline categories: possibly every message) is malformed the way its
category says, so that the garbage reaches the node's processing, not only its
synchroniser. Only message objects are built here (no rclpy node code);
``scripts/fuzz_nodes.py`` publishes them.

Categories (``CATEGORIES``; which apply depends on the input kinds):

* clouds: truncated / oversized data buffer, wrong point_step, wrong row_step, wrong
  height / width, missing fields, wrong datatypes, broken field layout (offsets, counts,
  duplicate names), NaN / inf and huge coordinates, empty cloud, invalid class
  probabilities, 2 million points (``huge_cloud``, a fixed few);
* boxes: zero / negative sizes, non-unit quaternions, NaN / inf scores, unknown classes
  (or none), NaN / inf and huge coordinates, empty array, bad ids, thousands of boxes
  (``thousands_of_boxes``, a fixed few);
* box variances: count mismatch, negative / NaN values, bad detection indices, empty;
* any input: mismatched frame_id, stamps in the future / past, time jumping backwards,
  invalid stamp (nanosec >= 1e9), a stamp that matches no other input, corrupt CDR bytes
  (``corrupt_cdr``: truncated, overwritten, huge lengths, other encapsulations, garbage;
  the case then holds ``bytes`` for that input, published as a serialized message; rmw
  drops what it cannot deserialize for typed subscriptions, raw ones get it as it is).

Messages of the template are shared between cases (never mutated): a case holds shallow
copies whose changed parts are new objects. Serialized bytes (:func:`serialized`,
:func:`restamp_bytes`) come from rclpy, which leaves CDR alignment padding unset: the
bytes of ``corrupt_cdr`` cases are seeded mutations of the template's serialization
(made once per template), so they repeat within a process, not byte for byte across runs.
"""
from __future__ import annotations

import array
import copy
import struct
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np
from lidar_quality_core.box_geometry import points_in_boxes
from lidar_quality_core.boxes import arrays_to_detections
from lidar_quality_core.conventions import probability_field
from lidar_quality_core.pointcloud import cloud_to_structured, create_cloud
from lidar_quality_core.synthetic import CLASS_NAMES as SYNTHETIC_CLASSES
from lidar_quality_core.synthetic import SENSOR_HEIGHT, synthetic_frame
from lidar_quality_core.time_sync import (HEADER_STAMP, NS_PER_SEC, ns_to_stamp,
                                          stamp_of_bytes)

__all__ = ["POINTS", "DETECTIONS", "VARIANCES", "CLOUD_CATEGORIES", "BOX_CATEGORIES",
           "VARIANCE_CATEGORIES", "COMMON_CATEGORIES", "CATEGORIES", "HEAVY_CATEGORIES",
           "HUGE_CLOUD_POINTS", "InputSpec", "input_spec", "FrameTemplate", "FuzzCase",
           "Fuzzer", "restamp", "serialized", "restamp_bytes", "stamp_of_bytes", "CDR_LE"]

POINTS, DETECTIONS, VARIANCES = "points", "detections", "variances"

CLOUD_CATEGORIES = ("truncated_buffer", "oversized_buffer", "wrong_point_step",
                    "wrong_row_step", "wrong_dimensions", "missing_fields", "wrong_datatypes",
                    "wrong_field_layout", "nan_inf_coordinates", "huge_coordinates", "empty",
                    "invalid_probabilities", "huge_cloud")
BOX_CATEGORIES = ("nonpositive_box_sizes", "non_unit_quaternions", "nan_scores",
                  "unknown_classes", "nan_inf_coordinates", "huge_coordinates", "empty",
                  "bad_ids", "thousands_of_boxes")
VARIANCE_CATEGORIES = ("variance_count_mismatch", "invalid_variances", "bad_indices", "empty")
COMMON_CATEGORIES = ("mismatched_frame_ids", "stamp_future", "stamp_past", "time_backwards",
                     "invalid_stamp", "unmatched_stamp", "corrupt_cdr")
CATEGORIES = tuple(dict.fromkeys(CLOUD_CATEGORIES + BOX_CATEGORIES + VARIANCE_CATEGORIES
                                 + COMMON_CATEGORIES))
#: Expensive categories: a fixed number of cases, not a share of the stream.
HEAVY_CATEGORIES = ("huge_cloud", "thousands_of_boxes")
HUGE_CLOUD_POINTS = 2_000_000

_KIND_CATEGORIES = {POINTS: CLOUD_CATEGORIES, DETECTIONS: BOX_CATEGORIES,
                    VARIANCES: VARIANCE_CATEGORIES}
#: Categories that may rewrite every message of the frame (target topic "*").
_FRAME_CATEGORIES = ("stamp_future", "stamp_past", "time_backwards", "invalid_stamp")
_UINT32_MAX = 2**32 - 1
_INT32_MAX = 2**31 - 1
_FAR_FUTURE_NS = 60 * NS_PER_SEC   # future / past stamps are at least this far off
_RESET_NS = NS_PER_SEC             # StampSynchronizer's default reset_on_backwards_ns
_WEIRD_STRINGS = ("", " ", "unicorn", "CAR", "car ", "/", "汽车", "\u0000", "x" * 4096)
_HUGE = (1e15, -1e15, 1e30, -1e30, 3.4e38, -3.4e38)
_NONFINITE = (float("nan"), float("inf"), float("-inf"))


@dataclass(frozen=True)
class InputSpec:
    """One input topic of a node and what a valid message on it looks like.

    ``kind``: ``POINTS`` (PointCloud2 with float32 x, y, z, intensity when ``xyz``, then
    one ``prob_dtype`` field per name of ``prob_fields``), ``DETECTIONS``
    (Detection3DArray of the ``source`` boxes: ``detections``, ``proposals`` or
    ``head<k>``) or ``VARIANCES`` (BoxVarianceArray of the boxes on topic ``of``).
    """

    topic: str
    kind: str
    prob_fields: tuple[str, ...] = ()
    prob_dtype: str = "float32"
    xyz: bool = True
    source: str = "detections"
    of: str | None = None

    def __post_init__(self):
        if self.kind not in _KIND_CATEGORIES:
            raise ValueError(f"unknown input kind {self.kind!r} of {self.topic}")
        if self.prob_dtype not in ("float32", "uint8"):
            raise ValueError(f"prob_dtype must be float32 or uint8, got {self.prob_dtype!r}")
        if self.kind == VARIANCES and not self.of:
            raise ValueError(f"variance input {self.topic} needs 'of' (its detection topic)")
        if self.kind == POINTS and not self.xyz and not self.prob_fields:
            raise ValueError(f"cloud input {self.topic} has no fields")


def input_spec(topic: str, type_name: str, prob_fields: Sequence[str] = (),
               separate_probabilities: bool = False) -> InputSpec:
    """InputSpec of an input of our nodes from its topic name and message type name.

    ``.../head_k`` carries head k's boxes, ``.../proposals`` proposals, other
    Detection3DArrays detections; ``.../head_k/variance`` the variances of head k; a cloud
    ``.../probabilities`` only ``prob_fields``; another cloud x, y, z, intensity plus
    ``prob_fields`` unless ``separate_probabilities``.
    """
    leaf = topic.rstrip("/").rsplit("/", 1)[-1]
    kind = type_name.rsplit("/", 1)[-1]
    if kind == "PointCloud2":
        if leaf == "probabilities":
            return InputSpec(topic, POINTS, prob_fields=tuple(prob_fields), xyz=False)
        return InputSpec(topic, POINTS,
                         prob_fields=() if separate_probabilities else tuple(prob_fields))
    if kind == "Detection3DArray":
        source = ("proposals" if leaf == "proposals" else
                  f"head{leaf[5:]}" if leaf.startswith("head_") else "detections")
        return InputSpec(topic, DETECTIONS, source=source)
    if kind == "BoxVarianceArray":
        return InputSpec(topic, VARIANCES, of=topic.rstrip("/").rsplit("/", 1)[0])
    raise ValueError(f"no fuzz input kind for {topic} of type {type_name}")


def _header(stamp_ns: int, frame_id: str):
    from std_msgs.msg import Header
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = ns_to_stamp(stamp_ns)
    return h


#: Serialized ROS messages start with the CDR encapsulation (little endian here); a
#: leading header's stamp follows (``time_sync.HEADER_STAMP``, ``stamp_of_bytes``).
CDR_LE = b"\x00\x01\x00\x00"


def serialized(msg) -> bytes:
    """CDR bytes of a message whose first field is its header (see :func:`restamp_bytes`)."""
    from rclpy.serialization import serialize_message
    data = serialize_message(msg)
    if data[:4] != CDR_LE or next(iter(msg.get_fields_and_field_types())) != "header":
        raise ValueError(f"{type(msg).__name__}: not little-endian CDR with a leading header")
    return data


def restamp_bytes(data: bytes, stamp_ns: int) -> bytes:
    """Serialized message ``data`` (from :func:`serialized`) with its header stamp set.
    Publishing bytes skips rclpy's per-message conversion (500 proposals: ~90 ms)."""
    buf = bytearray(data)
    HEADER_STAMP.pack_into(buf, 4, *ns_to_stamp(stamp_ns))
    return bytes(buf)


def restamp(msg, stamp_ns: int, frame_id: str | None = None):
    """Shallow copy of ``msg`` with a new header (``stamp_ns``, ``frame_id`` or its own)."""
    out = copy.copy(msg)
    out.header = _header(stamp_ns, msg.header.frame_id if frame_id is None else frame_id)
    return out


class FrameTemplate:
    """A valid frame for ``inputs`` (built once; :meth:`frame` restamps shallow copies).

    Boxes and points come from ``synthetic_frame(n_points, n_objects, n_proposals, seed)``;
    detections carry one hypothesis per name of ``classes`` (the top one first); head k
    is the detections with small seeded noise; class probabilities of a cloud follow the
    point's synthetic label (in-box -> the box's class, ground -> ``road``).
    """

    def __init__(self, inputs: Sequence[InputSpec], *, n_points: int = 3000, n_objects: int = 8,
                 n_proposals: int = 60, seed: int = 0,
                 classes: Sequence[str] = ("car", "truck", "pedestrian", "cyclist"),
                 frame_id: str = "lidar_top"):
        self.inputs = list(inputs)
        topics = [s.topic for s in self.inputs]
        if len(set(topics)) != len(topics):
            raise ValueError(f"duplicate input topics: {topics}")
        self.classes = tuple(classes)
        self.frame_id = frame_id
        self.n_points = int(n_points)
        f = synthetic_frame(n_points=n_points, n_objects=n_objects, n_proposals=n_proposals,
                            seed=seed)
        self.synthetic = f
        rng = np.random.default_rng(seed + 1)
        h = _header(0, frame_id)
        self.messages: dict[str, object] = {}
        self.boxes: dict[str, np.ndarray] = {}
        for spec in self.inputs:  # detections first: variances refer to them
            if spec.kind == DETECTIONS:
                boxes, cls, scores, ids = self._boxes(spec.source, f, rng)
                self.boxes[spec.topic] = boxes
                self.messages[spec.topic] = arrays_to_detections(
                    h, boxes, None, None, ids=ids, class_scores=self._class_scores(cls, scores))
        for spec in self.inputs:
            if spec.kind == POINTS:
                self.messages[spec.topic] = self._cloud(spec, f, rng, h)
            elif spec.kind == VARIANCES:
                if spec.of not in self.boxes:
                    raise ValueError(f"{spec.topic}: 'of' topic {spec.of} is not a detection input")
                dets = self.messages[spec.of].detections
                v = rng.uniform(0.005, 0.1, (len(dets), 7))
                self.messages[spec.topic] = _variance_array(h, v, [d.id for d in dets])

    def _boxes(self, source: str, f, rng):
        if source == "proposals":
            boxes, cls, scores = f.proposals, f.prop_classes, f.prop_scores
            ids = [str(i) for i in range(len(boxes))]
        elif source == "detections" or source.startswith("head"):
            boxes, cls, scores = f.detections.copy(), f.det_classes, f.det_scores.copy()
            prefix = "d"
            if source.startswith("head"):
                k = int(source[4:] or 0)
                r = np.random.default_rng([k, 17])
                boxes[:, :2] += r.normal(0.0, 0.1, (len(boxes), 2))
                scores = np.clip(scores + r.normal(0.0, 0.03, len(scores)), 0.05, 0.99)
                prefix = f"h{k}_"
            ids = [f"{prefix}{i}" for i in range(len(boxes))]
        else:
            raise ValueError(f"unknown box source {source!r}")
        return np.asarray(boxes, float), np.asarray(cls), np.asarray(scores, float), ids

    def _class_scores(self, cls, scores) -> dict[str, np.ndarray]:
        # The synthetic class gets the score, the other classes share part of the rest.
        names = [SYNTHETIC_CLASSES[c] for c in cls]
        idx = np.array([self.classes.index(n) if n in self.classes else 0 for n in names], int)
        k = len(self.classes)
        p = np.repeat(((1.0 - scores) * 0.5 / max(k - 1, 1))[:, None], k, axis=1)
        p[np.arange(len(idx)), idx] = scores
        return {c: p[:, j] for j, c in enumerate(self.classes)}

    def _cloud(self, spec: InputSpec, f, rng, h):
        cols: dict[str, np.ndarray] = {}
        if spec.xyz:
            cols.update(x=f.points[:, 0], y=f.points[:, 1], z=f.points[:, 2],
                        intensity=f.intensity)
        if spec.prob_fields:
            probs = _point_probabilities(f, spec.prob_fields, rng)
            for j, name in enumerate(spec.prob_fields):
                cols[name] = (np.rint(probs[:, j] * 255).astype(np.uint8)
                              if spec.prob_dtype == "uint8" else probs[:, j].astype(np.float32))
        return create_cloud(h, cols)

    def serialized(self, topic: str) -> bytes:
        """CDR bytes of the template message of ``topic`` (stamp 0), made once."""
        cache = self.__dict__.setdefault("_serialized", {})
        if topic not in cache:
            cache[topic] = serialized(self.messages[topic])
        return cache[topic]

    def frame(self, stamp_ns: int, frame_id: str | None = None) -> dict[str, object]:
        """Valid messages of every input (topic -> message), all stamped ``stamp_ns``."""
        return {t: restamp(m, stamp_ns, frame_id or self.frame_id)
                for t, m in self.messages.items()}

    def spec(self, topic: str) -> InputSpec:
        return next(s for s in self.inputs if s.topic == topic)


def _point_probabilities(f, names: Sequence[str], rng) -> np.ndarray:
    """(N, K) plausible softmax probabilities over ``names`` (field names, '_' for '-')."""
    norm = [probability_field(n) for n in names]
    label = np.full(len(f.points), norm.index("building") if "building" in norm else 0)
    if "road" in norm:
        label[f.points[:, 2] < -SENSOR_HEIGHT + 0.2] = norm.index("road")
    offsets, pts = points_in_boxes(f.points, f.gt_boxes)
    box_of = np.repeat(np.arange(len(f.gt_boxes)), np.diff(offsets))
    cls_names = np.array([SYNTHETIC_CLASSES[c] for c in f.gt_classes] + [""])
    thing = np.array([norm.index(c) if c in norm else -1 for c in cls_names[box_of]], int)
    ok = thing >= 0
    label[pts[ok]] = thing[ok]
    logits = rng.normal(0.0, 0.7, (len(label), len(names)))
    logits[np.arange(len(label)), label] += 4.0
    e = np.exp(logits - logits.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


def _variance_array(header, v: np.ndarray, ids, indices=None):
    from lidar_quality_msgs.msg import BoxVariance, BoxVarianceArray
    indices = range(len(v)) if indices is None else indices
    return BoxVarianceArray(header=header, variances=[
        BoxVariance(detection_index=int(i), detection_id=str(d), x=r[0], y=r[1], z=r[2],
                    length=r[3], width=r[4], height=r[5], yaw=r[6])
        for i, d, r in zip(indices, ids, np.asarray(v, float).tolist())])


@dataclass
class FuzzCase:
    """One frame of the stream: ``messages`` ([(topic, msg)], in publish order) with
    ``malformed`` of them broken as ``category`` says (``topic`` "*" = the whole frame)."""

    index: int
    category: str
    topic: str
    variant: str
    stamp_ns: int
    messages: list = field(default_factory=list)
    malformed: int = 1


class Fuzzer:
    """Deterministic stream of malformed frames for the inputs of ``template``.

    Cases cycle through every (category, topic) slot that applies to the inputs, in a
    seeded order, so categories get near-equal shares; ``huge_clouds`` 2-million-point
    clouds and ``box_floods`` arrays of thousands of boxes are placed at seeded positions
    (default: 3 and one per 500 cases). Frame stamps advance by ``period_ns`` from
    ``start_ns`` (default 10^6 s: room for the hour-long jumps back); ``time_backwards``
    cases move that clock back by the jump plus a sub-period offset, so that stamps seldom
    repeat.
    """

    def __init__(self, template: FrameTemplate, seed: int = 0, *,
                 start_ns: int = 1_000_000 * NS_PER_SEC,
                 period_ns: int = NS_PER_SEC // 10, huge_clouds: int = 3,
                 box_floods: int | None = None):
        self.template = template
        self.seed = int(seed)
        self.period_ns = int(period_ns)
        self.start_ns = int(start_ns)
        self._clock_ns = int(start_ns)
        self._recent_max_ns = int(start_ns)  # newest frame stamp since the last reset jump
        self.huge_clouds = int(huge_clouds)
        self.box_floods = box_floods
        self.topics = [s.topic for s in template.inputs]

    def slots(self) -> list[tuple[str, str]]:
        """(category, topic) pairs that apply to the inputs (heavy categories excluded;
        topic "?" for the categories of any input)."""
        out = []
        for spec in self.template.inputs:
            for cat in _KIND_CATEGORIES[spec.kind]:
                if cat in HEAVY_CATEGORIES:
                    continue
                if cat == "invalid_probabilities" and not spec.prob_fields:
                    continue
                if (cat in ("nan_inf_coordinates", "huge_coordinates") and spec.kind == POINTS
                        and not spec.xyz and spec.prob_dtype != "float32"):
                    continue  # no float field to hold the values
                out.append((cat, spec.topic))
        # Once per node, not per topic: the topic is drawn per case (see schedule).
        return out + [(cat, "?") for cat in COMMON_CATEGORIES]

    def schedule(self, n: int) -> list[tuple[str, str]]:
        """The (category, topic) of each of ``n`` cases."""
        rng = np.random.default_rng([self.seed, 1])
        heavy = []
        clouds = [s.topic for s in self.template.inputs if s.kind == POINTS]
        boxes = [s.topic for s in self.template.inputs if s.kind == DETECTIONS]
        floods = max(1, n // 500) if self.box_floods is None else int(self.box_floods)
        if clouds:
            heavy += [("huge_cloud", clouds[i % len(clouds)]) for i in range(self.huge_clouds)]
        if boxes:
            heavy += [("thousands_of_boxes", boxes[i % len(boxes)]) for i in range(floods)]
        heavy = heavy[: max(n - 1, 0)]
        slots = self.slots()
        plan: list[tuple[str, str]] = []
        while len(plan) < n - len(heavy):
            plan += [(c, t if t != "?" else self.topics[int(rng.integers(len(self.topics)))])
                     for c, t in (slots[i] for i in rng.permutation(len(slots)))]
        plan = plan[: n - len(heavy)]
        # Heavy cases never first: the node has seen ordinary traffic before.
        if heavy:
            positions = np.sort(rng.choice(np.arange(1, n), len(heavy), replace=False))
            for pos, slot in zip(positions.tolist(), heavy):
                plan.insert(pos, slot)
        return plan

    def cases(self, n: int) -> Iterator[FuzzCase]:
        """Generate ``n`` cases (lazily: heavy messages do not pile up in memory)."""
        for i, (cat, topic) in enumerate(self.schedule(n)):
            yield self.make_case(i, cat, topic)

    def next_stamp_ns(self) -> int:
        """The stamp of the stream's next frame: one period after its newest frame stamp
        since the clock last jumped back by more than the synchronisers' reset threshold
        (after a smaller jump the next frame must be newer than the frames before it)."""
        return max(self._clock_ns, self._recent_max_ns) + self.period_ns

    # -- one case ---------------------------------------------------------------------
    def make_case(self, index: int, category: str, topic: str) -> FuzzCase:
        rng = np.random.default_rng([self.seed, 2, index])
        if category == "time_backwards":  # behind the previous frame by the jump
            # plus a sub-period offset: the frames after the jump do not repeat the stamps
            # of earlier frames exactly (an output could not be told apart otherwise)
            jitter = int(rng.integers(1, max(self.period_ns, 2)))
            jump = int(float(rng.choice([0.05, 0.3, 0.9, 2.0, 60.0, 3600.0])) * NS_PER_SEC)
            old = self._clock_ns
            self._clock_ns = max(old - jump - jitter, NS_PER_SEC + jitter)
            if old - self._clock_ns > _RESET_NS:  # the jump made, not the one drawn
                self._recent_max_ns = self._clock_ns
        else:
            self._clock_ns += self.period_ns
        stamp = self._clock_ns
        self._recent_max_ns = max(self._recent_max_ns, stamp)
        frame = self.template.frame(stamp)
        case = FuzzCase(index, category, topic, "", stamp)
        if category in COMMON_CATEGORIES:
            case.variant = self._common(rng, category, topic, frame, case)
        elif category == "huge_cloud":
            # every cloud of the frame: clouds of one frame describe the same points
            clouds = [s for s in self.template.inputs if s.kind == POINTS]
            for spec in clouds:
                case.variant = self._points_huge_cloud(rng, frame[spec.topic], spec)
            if len(clouds) > 1:
                case.topic, case.malformed = "*", len(clouds)
        else:
            spec = self.template.spec(topic)
            mutate = getattr(self, f"_{spec.kind}_{category}")
            case.variant = mutate(rng, frame[topic], spec)
        order = rng.permutation(len(self.topics))
        case.messages = [(self.topics[j], frame[self.topics[j]]) for j in order]
        return case

    def _common(self, rng, category, topic, frame, case) -> str:
        whole = category in _FRAME_CATEGORIES and bool(rng.random() < 0.5)
        targets = list(frame) if whole or category == "time_backwards" else [topic]
        if len(targets) > 1:
            case.topic, case.malformed = "*", len(targets)
        if category == "time_backwards":
            return f"clock back to {case.stamp_ns / 1e9:.3f} s"
        if category == "mismatched_frame_ids":
            fid = str(rng.choice(["base_link", "", "map", "/lidar_top", "lidar_top ", "雷达",
                                  "f" * 2000]))
            frame[topic].header.frame_id = fid
            return f"frame_id {fid[:20]!r}"
        if category == "stamp_future":
            v = int(rng.integers(3))
            ahead = _FAR_FUTURE_NS + int(rng.integers(0, 10 * 365 * 86400)) * NS_PER_SEC
            ns = _INT32_MAX * NS_PER_SEC + NS_PER_SEC - 1 if v == 0 else case.stamp_ns + ahead
            for t in targets:
                frame[t].header.stamp.sec, frame[t].header.stamp.nanosec = ns_to_stamp(ns)
            when = "max int32 s" if v == 0 else f"+{(ns - case.stamp_ns) / 1e9:.0f} s"
            return f"{when} on {len(targets)}"
        if category == "stamp_past":
            v = int(rng.integers(4))
            sec, nsec = [(0, 0), (-1, 0), (-(2**31), 0),
                         ns_to_stamp(max(case.stamp_ns - _FAR_FUTURE_NS
                                         - int(rng.integers(0, 86400)) * NS_PER_SEC, 0))][v]
            for t in targets:
                frame[t].header.stamp.sec, frame[t].header.stamp.nanosec = sec, nsec
            return f"sec {sec} on {len(targets)}"
        if category == "invalid_stamp":
            nsec = int(rng.choice([NS_PER_SEC, NS_PER_SEC + 1, 2 * NS_PER_SEC, _UINT32_MAX]))
            for t in targets:
                frame[t].header.stamp.nanosec = nsec
            return f"nanosec {nsec} on {len(targets)}"
        if category == "corrupt_cdr":
            return self._corrupt_cdr(rng, topic, frame, case)
        if category == "unmatched_stamp":
            d = int(rng.choice([1, 1000, 1_000_000, 30_000_000, 49_999_999]))
            d = d if rng.random() < 0.5 else -d
            frame[topic].header.stamp.sec, frame[topic].header.stamp.nanosec = \
                ns_to_stamp(case.stamp_ns + d)
            return f"stamp {d:+d} ns"
        raise ValueError(category)

    def _corrupt_cdr(self, rng, topic, frame, case) -> str:
        data = bytearray(restamp_bytes(self.template.serialized(topic), case.stamp_ns))
        n = len(data)
        v = int(rng.integers(6))
        if v == 0:  # truncated, mostly after the stamp so that it still matches its frame
            k = int(rng.integers(12, n)) if rng.random() < 0.8 else int(rng.integers(0, 12))
            del data[k:]
            what = f"truncated to {k} of {n} bytes"
        elif v == 1:
            pos = rng.integers(12, n, int(rng.integers(1, 11)))
            data[pos[0]] ^= 0xFF  # at least one byte changes
            for p in pos[1:]:
                data[int(p)] = int(rng.integers(256))
            what = f"{len(pos)} bytes overwritten"
        elif v == 2:  # a length / count field (4-aligned after the encapsulation) made huge
            p = 4 + 4 * int(rng.integers(3, max((n - 8) // 4, 4)))
            p = min(p, n - 4)
            value = int(rng.choice([0xFFFFFFFF, 0x7FFFFFFF, 0x10000000, 0x00FFFFFF]))
            if struct.unpack_from("<I", data, p)[0] == value:
                value ^= 1
            struct.pack_into("<I", data, p, value)
            what = f"u32 {value:#x} at byte {p}"
        elif v == 3:
            data[:2] = bytes(rng.choice([b"\x00\x00", b"\x00\x02", b"\x00\x03", b"\xff\xff"]))
            what = f"encapsulation {bytes(data[:2]).hex()}"
        elif v == 4:  # garbage after a valid encapsulation and stamp
            m = int(rng.integers(0, 2 * n + 64))
            data[12:] = rng.integers(0, 256, m, dtype=np.uint8).tobytes()
            what = f"{m} random bytes"
        else:
            m = int(rng.integers(1, 4096))
            data += rng.integers(0, 256, m, dtype=np.uint8).tobytes()
            what = f"+{m} trailing bytes"
        frame[topic] = bytes(data)
        return what

    # -- clouds -----------------------------------------------------------------------
    @staticmethod
    def _points_truncated_buffer(rng, msg, spec) -> str:
        n = len(msg.data)
        k = int(rng.choice([0, 1, max(n - 1, 0), max(n - msg.point_step, 0),
                            int(rng.integers(0, max(n, 1)))]))
        msg.data = msg.data[:k]
        return f"{k} of {n} bytes"

    @staticmethod
    def _points_oversized_buffer(rng, msg, spec) -> str:
        m = int(rng.choice([1, max(msg.point_step - 1, 1), msg.point_step, len(msg.data),
                            int(rng.integers(1, 100_000))]))
        msg.data = msg.data + array.array("B", rng.integers(0, 256, m, dtype=np.uint8).tobytes())
        return f"+{m} bytes"

    @staticmethod
    def _points_wrong_point_step(rng, msg, spec) -> str:
        step = msg.point_step
        new = int(rng.choice([0, 1, step - 1, step + 1, step // 2, 2 * step, _UINT32_MAX]))
        msg.point_step = new
        if rng.random() < 0.5:  # keep row_step consistent with the lie
            msg.row_step = min(new * msg.width, _UINT32_MAX)
        return f"point_step {step} -> {new}"

    @staticmethod
    def _points_wrong_row_step(rng, msg, spec) -> str:
        rs = msg.row_step
        new = int(rng.choice([0, 1, rs - 1, rs + 1, rs + msg.point_step, 2 * rs, _UINT32_MAX]))
        msg.row_step = new
        return f"row_step {rs} -> {new}"

    @staticmethod
    def _points_wrong_dimensions(rng, msg, spec) -> str:
        w = msg.width
        v = int(rng.integers(6))
        msg.height, msg.width = [(0, w), (2, w), (1, w + 1), (1, _UINT32_MAX),
                                 (_UINT32_MAX, _UINT32_MAX), (3, w // 3 + 1)][v]
        if v == 5:  # organized, row_step of the claimed width: a lie about the layout
            msg.row_step = msg.width * msg.point_step
        return f"height {msg.height} width {msg.width}"

    @staticmethod
    def _points_missing_fields(rng, msg, spec) -> str:
        names = [f.name for f in msg.fields]
        k = int(rng.integers(1, len(names) + 1))
        drop = set(rng.choice(names, k, replace=False).tolist())
        # The required fields come first: make sure at least one of them goes.
        if not drop & set(names[:4]):
            drop.add(names[int(rng.integers(min(4, len(names))))])
        msg.fields = [f for f in msg.fields if f.name not in drop]
        return f"without {sorted(drop)[:6]}"

    @staticmethod
    def _points_wrong_datatypes(rng, msg, spec) -> str:
        fields = [copy.copy(f) for f in msg.fields]
        if rng.random() < 0.15:
            msg.is_bigendian = not msg.is_bigendian
            return f"is_bigendian {msg.is_bigendian}"
        k = int(rng.integers(len(fields)))
        old = fields[k].datatype
        new = int(rng.choice([d for d in (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 42, 255) if d != old]))
        fields[k].datatype = new
        msg.fields = fields
        return f"{fields[k].name}: datatype {old} -> {new}"

    @staticmethod
    def _points_wrong_field_layout(rng, msg, spec) -> str:
        fields = [copy.copy(f) for f in msg.fields]
        k = int(rng.integers(len(fields)))
        v = int(rng.integers(4))
        if v == 0:
            old = fields[k].offset
            fields[k].offset = int(rng.choice([msg.point_step - 1, msg.point_step, _UINT32_MAX,
                                               fields[(k + 1) % len(fields)].offset + 1]))
            if fields[k].offset == old:
                fields[k].offset = msg.point_step
            what = f"offset {fields[k].offset}"
        elif v == 1:
            fields[k].count = int(rng.choice([0, 2, 3, 1000, _UINT32_MAX]))
            what = f"count {fields[k].count}"
        elif v == 2:
            fields[k].name = fields[(k + 1) % len(fields)].name
            what = "duplicate name"
        else:
            fields[k].name = str(rng.choice(_WEIRD_STRINGS))
            what = f"renamed {fields[k].name[:10]!r}"
        msg.fields = fields
        return f"{msg.fields[k].name[:12]}: {what}"

    @staticmethod
    def _set_values(msg, rng, spec, values, frac_choices=(None, 0.01, 0.5, 1.0)) -> str:
        arr = cloud_to_structured(msg).copy()
        names = ["x", "y", "z"] if spec.xyz else list(spec.prob_fields)
        if spec.xyz and rng.random() < 0.2:
            names = ["intensity"]
        if spec.prob_fields and spec.prob_dtype == "float32" and rng.random() < 0.2:
            names = list(spec.prob_fields)
        frac = frac_choices[int(rng.integers(len(frac_choices)))]
        n = len(arr)
        idx = (np.array([int(rng.integers(n))]) if frac is None
               else np.flatnonzero(rng.random(n) < frac))
        names = [nm for nm in names if arr.dtype[nm].kind == "f"]
        for name in names:
            col = arr[name]
            col[idx] = rng.choice(values, len(idx)).astype(col.dtype)
        msg.data = array.array("B", arr.tobytes())
        return f"{len(idx)} points, {names[:3]}"

    def _points_nan_inf_coordinates(self, rng, msg, spec) -> str:
        return self._set_values(msg, rng, spec, np.array(_NONFINITE))

    def _points_huge_coordinates(self, rng, msg, spec) -> str:
        return self._set_values(msg, rng, spec, np.array(_HUGE))

    @staticmethod
    def _points_empty(rng, msg, spec) -> str:
        v = int(rng.integers(3))
        msg.width, msg.height, msg.row_step = (0, 1, 0) if v < 2 else (0, 0, 0)
        msg.data = array.array("B")
        if v == 1:
            msg.fields, msg.point_step = [], 0
        return ["width 0", "width 0, no fields", "height 0"][v]

    @staticmethod
    def _points_invalid_probabilities(rng, msg, spec) -> str:
        arr = cloud_to_structured(msg).copy()
        names = list(spec.prob_fields)
        v = int(rng.integers(4))
        if spec.prob_dtype == "uint8":
            fill = [0, 255, 0, 255][v]
            for n in names:
                arr[n] = fill if v < 2 else rng.integers(0, 256, len(arr))
            what = ["all 0", "all 255", "random", "random"][v]
        else:
            vals = [lambda s: -rng.random(s), lambda s: 1.0 + rng.random(s) * 100,
                    lambda s: np.zeros(s), lambda s: rng.random(s) * 5.0][v]
            for n in names:
                arr[n] = vals(len(arr)).astype(np.float32)
            what = ["negative", "> 1", "all 0", "unnormalised"][v]
        msg.data = array.array("B", arr.tobytes())
        return what

    def _points_huge_cloud(self, rng, msg, spec) -> str:
        base = cloud_to_structured(msg)
        reps = -(-HUGE_CLOUD_POINTS // len(base))
        arr = np.tile(base, reps)[:HUGE_CLOUD_POINTS]
        if spec.xyz:  # spread the copies so they are not 2 M duplicates
            arr["x"] += rng.normal(0.0, 0.05, len(arr)).astype(np.float32)
            arr["y"] += rng.normal(0.0, 0.05, len(arr)).astype(np.float32)
        msg.data = array.array("B", arr.tobytes())
        msg.width, msg.height = len(arr), 1
        msg.row_step = msg.width * msg.point_step
        return f"{len(arr)} points"

    # -- boxes ------------------------------------------------------------------------
    @staticmethod
    def _own(msg, idx) -> list:
        """Replace detections ``idx`` of ``msg`` by deep copies; returns them."""
        dets = list(msg.detections)
        for i in idx:
            dets[i] = copy.deepcopy(dets[i])
        msg.detections = dets
        return [dets[i] for i in idx]

    @staticmethod
    def _pick(rng, n: int) -> np.ndarray:
        if n == 0:
            return np.zeros(0, int)
        v = int(rng.integers(3))
        k = 1 if v == 0 else (n if v == 2 else int(rng.integers(1, n + 1)))
        return np.sort(rng.choice(n, k, replace=False))

    def _detections_nonpositive_box_sizes(self, rng, msg, spec) -> str:
        idx = self._pick(rng, len(msg.detections))
        for d in self._own(msg, idx):
            for ax in ("x", "y", "z"):
                if rng.random() < 0.5 or ax == "x":
                    setattr(d.bbox.size, ax, float(rng.choice([0.0, -0.0, -1e-9, -1.0, -1e9])))
        return f"{len(idx)} boxes"

    def _detections_non_unit_quaternions(self, rng, msg, spec) -> str:
        idx = self._pick(rng, len(msg.detections))
        v = int(rng.integers(4))
        for d in self._own(msg, idx):
            o = d.bbox.center.orientation
            if v == 0:
                o.x = o.y = o.z = o.w = 0.0
            elif v == 1:
                s = float(rng.choice([1e-12, 0.5, 2.0, 1e9]))
                o.x, o.y, o.z, o.w = o.x * s, o.y * s, o.z * s, o.w * s
            elif v == 2:  # tilted (roll / pitch the boxes cannot have) and not unit
                q = rng.normal(size=4)
                o.x, o.y, o.z, o.w = (q / np.linalg.norm(q) * rng.uniform(1.5, 3.0)).tolist()
            else:
                q = rng.normal(size=4) * 10 ** rng.uniform(-6, 6)
                o.x, o.y, o.z, o.w = q.tolist()
        return f"{len(idx)} boxes, {['zero', 'scaled', 'tilted', 'random'][v]}"

    def _detections_nan_scores(self, rng, msg, spec) -> str:
        idx = self._pick(rng, len(msg.detections))
        for d in self._own(msg, idx):
            for r in d.results:
                if rng.random() < 0.7:
                    r.hypothesis.score = float(rng.choice(
                        [np.nan, np.inf, -np.inf, -1.0, 2.0, 1e308]))
        return f"{len(idx)} boxes"

    def _detections_unknown_classes(self, rng, msg, spec) -> str:
        idx = self._pick(rng, len(msg.detections))
        v = int(rng.integers(3))
        for d in self._own(msg, idx):
            if v == 0:
                for r in d.results:
                    r.hypothesis.class_id = str(rng.choice(_WEIRD_STRINGS))
            elif v == 1:
                d.results = []
            else:  # many hypotheses of classes nobody knows
                from vision_msgs.msg import ObjectHypothesisWithPose
                extra = []
                for j in range(int(rng.integers(5, 50))):
                    hyp = ObjectHypothesisWithPose()
                    hyp.hypothesis.class_id = f"class_{j}"
                    hyp.hypothesis.score = float(rng.random())
                    extra.append(hyp)
                d.results = list(d.results) + extra
        return f"{len(idx)} boxes, {['unknown ids', 'no hypothesis', 'extra classes'][v]}"

    def _detections_nan_inf_coordinates(self, rng, msg, spec) -> str:
        return self._box_values(rng, msg, _NONFINITE)

    def _detections_huge_coordinates(self, rng, msg, spec) -> str:
        return self._box_values(rng, msg, _HUGE)

    def _box_values(self, rng, msg, values) -> str:
        idx = self._pick(rng, len(msg.detections))
        part = str(rng.choice(["position", "size", "orientation"]))
        for d in self._own(msg, idx):
            obj = (d.bbox.center.position if part == "position" else
                   d.bbox.size if part == "size" else d.bbox.center.orientation)
            axes = ("x", "y", "z", "w") if part == "orientation" else ("x", "y", "z")
            for ax in axes:
                if rng.random() < 0.5 or ax == "x":
                    setattr(obj, ax, float(rng.choice(values)))
        return f"{len(idx)} boxes, {part}"

    @staticmethod
    def _detections_empty(rng, msg, spec) -> str:
        msg.detections = []
        return "0 boxes"

    def _detections_bad_ids(self, rng, msg, spec) -> str:
        n = len(msg.detections)
        if n == 0:
            return "no boxes"
        v = int(rng.integers(3))
        idx = np.arange(n)
        for d in self._own(msg, idx):
            d.id = ["", "dup", str(rng.choice(_WEIRD_STRINGS))][v]
        return ["empty ids", "duplicate ids", "weird ids"][v]

    def _detections_thousands_of_boxes(self, rng, msg, spec) -> str:
        n = int(rng.integers(1000, 5001))
        clustered = bool(rng.random() < 0.3)
        span = 4.0 if clustered else 80.0
        boxes = np.column_stack([rng.uniform(-span, span, (n, 2)), rng.uniform(-1.5, 0.5, n),
                                 rng.uniform(0.5, 5.0, (n, 3)), rng.uniform(-np.pi, np.pi, n)])
        scores = rng.uniform(0.05, 0.95, n)
        k = len(self.template.classes)
        cls = rng.integers(k, size=n)
        p = np.repeat(((1.0 - scores) / (2 * max(k - 1, 1)))[:, None], k, axis=1)
        p[np.arange(n), cls] = scores
        classes = self.template.classes
        out = arrays_to_detections(msg.header, boxes, None, None, ids=[f"f{i}" for i in range(n)],
                                   class_scores={c: p[:, j] for j, c in enumerate(classes)})
        msg.detections = out.detections
        return f"{n} boxes{' clustered' if clustered else ''}"

    # -- box variances ----------------------------------------------------------------
    @staticmethod
    def _variances_variance_count_mismatch(rng, msg, spec) -> str:
        n = len(msg.variances)
        new = int(rng.choice([0, max(n - 1, 0), n + 1, 2 * n + 3, 1000]))
        vs = list(msg.variances)[:new]
        while len(vs) < new:
            v = copy.copy(vs[-1]) if vs else None
            if v is None:
                from lidar_quality_msgs.msg import BoxVariance
                v = BoxVariance()
            v.detection_index = len(vs)
            v.detection_id = f"extra{len(vs)}"
            vs.append(v)
        msg.variances = vs
        return f"{n} -> {new} entries"

    @staticmethod
    def _variances_invalid_variances(rng, msg, spec) -> str:
        vs = [copy.copy(v) for v in msg.variances]
        vals = [np.nan, np.inf, -np.inf, -1.0, -1e-12, 1e300]
        axes = ("x", "y", "z", "length", "width", "height", "yaw")
        hit = rng.random((len(vs), len(axes))) < 0.3
        if hit.size:
            hit.flat[int(rng.integers(hit.size))] = True  # at least one
        for v, row in zip(vs, hit):
            for ax in np.array(axes)[row]:
                setattr(v, str(ax), float(rng.choice(vals)))
        msg.variances = vs
        return f"{int(hit.sum())} values in {len(vs)} entries"

    @staticmethod
    def _variances_bad_indices(rng, msg, spec) -> str:
        vs = [copy.copy(v) for v in msg.variances]
        v_ = int(rng.integers(3))
        for j, v in enumerate(vs):
            if v_ == 0:
                v.detection_index = int(rng.choice([len(vs), len(vs) + 7, _UINT32_MAX]))
            elif v_ == 1:
                v.detection_id = str(rng.choice(_WEIRD_STRINGS))
            else:
                v.detection_index = len(vs) - 1 - j  # reversed order
        msg.variances = vs
        return ["index out of range", "ids unknown", "reversed"][v_]

    @staticmethod
    def _variances_empty(rng, msg, spec) -> str:
        msg.variances = []
        return "0 entries"

