"""Frames of a perception bag: every message of one stamp together, decoded.

A perception bag (``reference-perception bag`` / ``split``, or a recording of a user's own
stack) holds per lidar scan the cloud and, stamped like it, the perception outputs and,
for simulated or labelled data, the ground truth. Training and evaluation of the three
methods read it through :func:`perception_frames`, then convert the messages with the same
functions the nodes use, so offline features are the online ones.
"""
from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

from .bag_io import UnknownTypes, bag_topics, read_bag

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
_HEAD_KEY = re.compile(r"head_(\d+)(/variance)?")
#: The topic keys (``--topic KEY=TOPIC``): the nodes' input names without ``input/``.
TOPIC_KEYS = (*DEFAULT_TOPICS, "head_<k>", "head_<k>/variance")
TOPIC_HELP = ("bag topic of an input, as KEY=TOPIC (repeatable), e.g. "
              "points=/sensing/lidar/top/pointcloud; keys: " + ", ".join(TOPIC_KEYS))


def check_topic_key(key: str) -> None:
    """``ValueError`` naming the known keys unless ``key`` is one."""
    if key not in DEFAULT_TOPICS and not _HEAD_KEY.fullmatch(key):
        raise ValueError(f"unknown topic key {key!r} (known: {', '.join(TOPIC_KEYS)})")


def topic_of(key: str, topics: dict[str, str] | None = None) -> str:
    """The bag topic of ``key``: ``topics[key]`` if given, else its default name."""
    check_topic_key(key)
    if topics and key in topics:
        return topics[key]
    m = _HEAD_KEY.fullmatch(key)
    if m:
        return (HEAD_VARIANCE_TOPIC if m.group(2) else HEAD_TOPIC).format(k=int(m.group(1)))
    return DEFAULT_TOPICS[key]


def parse_topic_options(items: Sequence[str] | None) -> dict[str, str]:
    """``["points=/a", ...]`` -> ``{"points": "/a"}``; ``ValueError`` for a malformed item
    or an unknown key (naming the known keys)."""
    out: dict[str, str] = {}
    for item in items or ():
        key, eq, topic = item.partition("=")
        key, topic = key.strip(), topic.strip()
        if not eq or not key or not topic.startswith("/") or len(topic) < 2:
            raise ValueError(f"--topic {item!r}: expected KEY=/topic/name "
                             f"(keys: {', '.join(TOPIC_KEYS)})")
        check_topic_key(key)
        if key in out and out[key] != topic:
            raise ValueError(f"--topic {key} given twice ({out[key]}, {topic})")
        out[key] = topic
    return out


def topic_option_type(item: str) -> tuple[str, str]:
    """argparse ``type=`` for a repeated ``--topic KEY=TOPIC`` (a bad one is a usage
    error naming the known keys); ``dict(args.topic)`` gives the mapping."""
    import argparse

    try:
        return next(iter(parse_topic_options([item]).items()))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_topic_option(parser) -> None:
    """The ``--topic KEY=TOPIC`` option of the bag reading / writing CLIs."""
    parser.add_argument("--topic", action="append", default=[], type=topic_option_type,
                        metavar="KEY=TOPIC", help=TOPIC_HELP)


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


def head_count(bag: Path | str, topics: dict[str, str] | None = None) -> int:
    """Number of consecutive ``head_k`` topics in the bag (names from ``topics``, else
    the defaults)."""
    present = bag_topics(bag)
    k = 0
    while topic_of(f"head_{k}", topics) in present:
        k += 1
    return k


def perception_frames(bag: Path | str, *, want=("points", "detections", "proposals",
                                                "gt_objects"),
                      heads: int | None = 0, topics: dict[str, str] | None = None,
                      require: str = "points", window: int = 16) -> Iterator[PerceptionFrame]:
    """Yield one :class:`PerceptionFrame` per stamp of ``require``'s topic, in time order.

    ``want`` names the keys of ``DEFAULT_TOPICS`` to decode; ``topics`` (key -> topic,
    ``--topic`` options: ``parse_topic_options``) overrides their names and the heads';
    ``heads``: how many ``head_k`` (+ variance) topics to read (``None``: all in the bag).
    Topics whose type has no rclpy class here are left out with one warning per type.
    Messages are grouped by header stamp, not log time; a frame is complete once
    ``window`` newer stamps have been seen (recorders log a scan's outputs shortly after
    it), which keeps memory bounded on long bags.
    """
    for key in (*want, require, *(topics or {})):
        check_topic_key(key)
    names = {k: topic_of(k, topics) for k in DEFAULT_TOPICS}
    present = bag_topics(bag)
    if names[require] not in present:
        raise ValueError(f"{bag}: no topic {names[require]} (topics: {sorted(present)}; "
                         f"name it with --topic {require}=TOPIC)")
    k_heads = head_count(bag, topics) if heads is None else int(heads)
    by_topic = {names[k]: k for k in want if names[k] in present}
    by_topic[names[require]] = require
    for k in range(k_heads):
        by_topic[topic_of(f"head_{k}", topics)] = ("head", k)
        if topic_of(f"head_{k}/variance", topics) in present:
            by_topic[topic_of(f"head_{k}/variance", topics)] = ("var", k)
    unknown = UnknownTypes(lambda t: print(f"{bag}: warning: {t}", file=sys.stderr),
                           "not read")
    readable = set(unknown.check_all({t: present[t] for t in by_topic if t in present}))
    if names[require] not in readable:
        raise ValueError(f"{bag}: topic {names[require]} has type {present[names[require]]}, "
                         f"which is not available here")
    by_topic = {t: k for t, k in by_topic.items() if t in readable}

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
