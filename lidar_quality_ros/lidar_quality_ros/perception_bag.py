"""Frames of a perception bag: every message of one stamp together, decoded.

A perception bag (``reference-perception bag`` / ``split``, or a recording of a user's own
stack) holds per lidar scan the cloud and, stamped like it, the perception outputs and,
for simulated or labelled data, the ground truth. Training and evaluation of the three
methods read it through :func:`perception_frames`, then convert the messages with the same
functions the nodes use, so offline features are the online ones.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

from .bag_io import bag_topics, read_bag

#: Default topics of the reference perception bags (``reference_perception.cli``).
DEFAULT_TOPICS = {
    "points": "/lidar/points",
    "points_gt": "/lidar/points_gt",
    "gt_objects": "/lidar/gt_objects",
    "detections": "/perception/detections",
    "proposals": "/perception/proposals",
    "segmentation": "/perception/segmentation",
}
HEAD_TOPIC = "/perception/head_{k}"
HEAD_VARIANCE_TOPIC = "/perception/head_{k}/variance"


@dataclass
class PerceptionFrame:
    """Decoded rclpy messages of one stamp; ``None`` where the bag has no such message."""

    bag: str
    index: int
    stamp_ns: int
    messages: dict[str, object] = field(default_factory=dict)
    heads: list = field(default_factory=list)            # Detection3DArray per head
    head_variances: list = field(default_factory=list)   # BoxVarianceArray or None per head

    def __getattr__(self, key):
        # points, points_gt, gt_objects, detections, proposals, segmentation
        try:
            return self.__dict__["messages"].get(key)
        except KeyError:
            raise AttributeError(key) from None


def head_count(bag: Path | str) -> int:
    """Number of consecutive ``head_k`` topics in the bag."""
    topics = bag_topics(bag)
    k = 0
    while HEAD_TOPIC.format(k=k) in topics:
        k += 1
    return k


def perception_frames(bag: Path | str, *, want=("points", "detections", "proposals",
                                                "gt_objects"),
                      heads: int | None = 0, topics: dict[str, str] | None = None,
                      require: str = "points", window: int = 16) -> Iterator[PerceptionFrame]:
    """Yield one :class:`PerceptionFrame` per stamp of ``require``'s topic, in time order.

    ``want`` names the keys of ``DEFAULT_TOPICS`` (or of ``topics``, which overrides them)
    to decode; ``heads``: how many ``head_k`` (+ variance) topics to read (``None``: all
    in the bag). Messages are grouped by header stamp, not log time; a frame is complete
    once ``window`` newer stamps have been seen (recorders log a scan's outputs shortly
    after it), which keeps memory bounded on long bags.
    """
    names = {**DEFAULT_TOPICS, **(topics or {})}
    unknown = set(want) - set(names)
    if unknown:
        raise ValueError(f"unknown frame keys {sorted(unknown)} (known: {sorted(names)})")
    present = bag_topics(bag)
    if names[require] not in present:
        raise ValueError(f"{bag}: no topic {names[require]} (topics: {sorted(present)})")
    k_heads = head_count(bag) if heads is None else int(heads)
    by_topic = {names[k]: k for k in want if names[k] in present}
    by_topic[names[require]] = require
    for k in range(k_heads):
        by_topic[HEAD_TOPIC.format(k=k)] = ("head", k)
        if HEAD_VARIANCE_TOPIC.format(k=k) in present:
            by_topic[HEAD_VARIANCE_TOPIC.format(k=k)] = ("var", k)

    pending: dict[int, PerceptionFrame] = {}
    n = 0

    def flush(keep: int):
        nonlocal n
        for stamp in sorted(pending)[:max(len(pending) - keep, 0)]:
            f = pending.pop(stamp)
            if f.messages.get(require) is not None:
                f.index = n
                n += 1
                yield f

    for m in read_bag(bag, topics=set(by_topic)):
        msg = m.decode()
        st = msg.header.stamp
        stamp = st.sec * 1_000_000_000 + st.nanosec
        f = pending.get(stamp)
        if f is None:
            f = pending[stamp] = PerceptionFrame(str(bag), -1, stamp, {}, [None] * k_heads,
                                                 [None] * k_heads)
            yield from flush(window)
        key = by_topic[m.topic]
        if isinstance(key, tuple):
            (f.heads if key[0] == "head" else f.head_variances)[key[1]] = msg
        else:
            f.messages[key] = msg
    yield from flush(0)


def resolve_bags(paths: Sequence) -> list[Path]:
    """Bag directories of ``paths``: a bag itself (has ``metadata.yaml``) or a directory
    whose sub-directories are bags (e.g. ``data/perception/meta_train``), sorted."""
    out = []
    for p in map(Path, paths):
        if (p / "metadata.yaml").exists():
            out.append(p)
            continue
        subs = sorted(q for q in p.iterdir() if (q / "metadata.yaml").exists()) if p.is_dir() else []
        if not subs:
            raise FileNotFoundError(f"{p}: not a rosbag2 directory and holds none")
        out.extend(subs)
    return out


def bag_group(bag: Path | str) -> str:
    """Group name of a bag (the unit of grouped splits): ``<parent>/<name>``, e.g.
    ``meta_train/seq_03``."""
    bag = Path(bag)
    return f"{bag.parent.name}/{bag.name}" if bag.parent.name else bag.name
