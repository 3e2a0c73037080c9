"""LiDAR-MIMO datasets from perception bags: merged clusters with their features and targets,
the single-head baseline detections, and each frame's ground truth.

Per frame of a perception bag (``perception_frames``: the K ``/perception/head_k`` (+
variance) messages, ``/lidar/points``, ``/lidar/points_gt``, ``/lidar/gt_objects``):

* merged detections: ``pipeline.frame_features`` (the node's own decoding, merging and
  features) with ``use_points=True``; the cluster-statistics features are its first
  ``len(STAT_FEATURES)`` columns (identical to ``use_points=False``). Kept per detection:
  features, merged box, merged class distribution (background column 0), label, score,
  predictive variance (epistemic + aleatoric, yaw of the top member);
* single-head baseline: head 0 alone (``pipeline.head_detections``, same conversion): box,
  class distribution, label (best foreground class), score, its predicted variance. Boxes
  the node could not use are left out (counted in ``info["dropped_single"]``);
* targets of both: ``iou_class`` = BEV IoU with the best ground-truth box of the
  detection's class (``detection_eval.match_frame``'s ``iou_same_class``), ``iou_any`` with
  the best one of any class. The meta classifier's target is ``iou_class >= TP_IOU`` (0.5):
  class-aware like a TP of the paper's evaluation, but without the one-to-one matching, which
  depends on the order of the very scores being learnt (a duplicate would be a TP here; with
  merged clusters duplicates are rare). The regressor's target is ``iou_class``;
* ground truth: boxes, class names, ids and the points of each object (``/lidar/points_gt``
  instance counts; without that topic, the cloud points inside the box). ``gt_ignore``
  marks boxes with fewer than ``EVAL_MIN_POINTS`` points or beyond ``EVAL_MAX_RANGE``, as
  the reference detector's evaluation (``reference_perception.detector.gt_ignore_mask``).

Group = sequence (one bag). One ``.npz`` per bag under ``cache_dir``, keyed by the bag's
files (path, size, mtime), the settings and the code of this module, ``pipeline``,
``merging`` and ``uncertainty``.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from lidar_quality_training.cache import source_hash
from lidar_quality_core.conventions import TP_IOU

from mimo_ros.pipeline import MimoSettings

__all__ = ["TP_IOU", "EVAL_MIN_POINTS", "EVAL_MAX_RANGE", "MimoDataset", "read_bag",
           "load_bags", "resolve_bags"]

CACHE_VERSION = 1
def _eval_defaults() -> tuple[int, float]:
    from reference_perception.clustering import ClusterConfig
    from reference_perception.detector import EVAL_MIN_POINTS as min_points

    return int(min_points), float(ClusterConfig().max_range)


EVAL_MIN_POINTS, EVAL_MAX_RANGE = _eval_defaults()

# row tables: merged detections ("m_"), single-head detections ("s_"), frames, GT boxes
_MERGED = ("X", "m_box", "m_probs", "m_label", "m_score", "m_var", "m_iou_class", "m_iou_any",
           "m_frame")
_SINGLE = ("s_box", "s_probs", "s_label", "s_score", "s_var", "s_iou_class", "s_iou_any",
           "s_frame")
_FRAMES = ("frame_group", "frame_source", "frame_stamp", "frame_heads", "gt_offsets")
_GT = ("gt_box", "gt_label", "gt_id", "gt_points")
_ALL = _MERGED + _SINGLE + _FRAMES + _GT


@dataclass
class MimoDataset:
    """Merged (``m_*``, ``X``) and single-head (``s_*``) detections of a set of frames.

    Labels are class columns 1..C of the distributions (column 0 = background);
    ``class_names[label - 1]`` names them. Frame ``k``'s ground truth is rows
    ``gt_offsets[k]:gt_offsets[k + 1]`` of the ``gt_*`` arrays.
    """

    class_names: tuple
    feature_names: tuple        # columns of X (cluster statistics + point features)
    X: np.ndarray               # (n, F)
    m_box: np.ndarray           # (n, 7) merged box
    m_probs: np.ndarray         # (n, 1 + C) merged class distribution
    m_label: np.ndarray         # (n,) int column
    m_score: np.ndarray         # (n,) probability of the label
    m_var: np.ndarray           # (n, 7) predictive variance
    m_iou_class: np.ndarray     # (n,) BEV IoU with the best GT box of its class
    m_iou_any: np.ndarray       # (n,) with the best GT box of any class
    m_frame: np.ndarray         # (n,) frame row
    s_box: np.ndarray           # (s, 7) head 0 boxes
    s_probs: np.ndarray         # (s, 1 + C)
    s_label: np.ndarray         # (s,)
    s_score: np.ndarray         # (s,)
    s_var: np.ndarray           # (s, 7) head 0's predicted variances
    s_iou_class: np.ndarray     # (s,)
    s_iou_any: np.ndarray       # (s,)
    s_frame: np.ndarray         # (s,)
    frame_group: np.ndarray     # (f,) str sequence
    frame_source: np.ndarray    # (f,) str bag path
    frame_stamp: np.ndarray     # (f,) int64 header stamp [ns]
    frame_heads: np.ndarray     # (f,) int heads present
    gt_offsets: np.ndarray      # (f + 1,)
    gt_box: np.ndarray          # (g, 7)
    gt_label: np.ndarray        # (g,) str class name
    gt_id: np.ndarray           # (g,) str
    gt_points: np.ndarray       # (g,) int points of the object
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.m_score)

    @property
    def n_frames(self) -> int:
        return len(self.frame_group)

    @property
    def tp(self) -> np.ndarray:
        """(n,) bool meta classification target: ``m_iou_class >= TP_IOU``."""
        return self.m_iou_class >= TP_IOU

    @property
    def group(self) -> np.ndarray:
        """(n,) sequence of each merged detection."""
        return self.frame_group[self.m_frame]

    @property
    def groups(self) -> list[str]:
        return list(dict.fromkeys(self.frame_group.tolist()))

    def features(self, use_points: bool) -> tuple[np.ndarray, tuple]:
        """``(X, names)`` of the model with or without the point features."""
        names = MimoSettings(use_points=use_points).feature_names()
        if tuple(self.feature_names[:len(names)]) != tuple(names):
            raise ValueError(f"dataset features {self.feature_names} do not start with {names}")
        return self.X[:, :len(names)], tuple(names)

    def labels(self, which: str = "m") -> np.ndarray:
        """Class names of the merged (``"m"``) or single-head (``"s"``) detections."""
        lab = getattr(self, f"{which}_label")
        return np.asarray(self.class_names, dtype=object)[lab - 1] if len(lab) else \
            np.zeros(0, dtype=object)

    def gt_of(self, k: int):
        """``(boxes, labels, ids, points)`` of frame ``k``."""
        a, b = self.gt_offsets[k], self.gt_offsets[k + 1]
        return self.gt_box[a:b], self.gt_label[a:b], self.gt_id[a:b], self.gt_points[a:b]

    def gt_ignore(self, min_points: int = EVAL_MIN_POINTS,
                  max_range: float = EVAL_MAX_RANGE) -> np.ndarray:
        """(g,) bool: ground truth left out of AP and partitions (module docstring)."""
        r = np.hypot(self.gt_box[:, 0], self.gt_box[:, 1])
        return (self.gt_points < min_points) | (r > max_range)

    def subset_frames(self, frames) -> "MimoDataset":
        """The frames ``frames`` (indices, kept in the given order) and their rows."""
        frames = np.asarray(frames, np.int64)
        new = np.full(self.n_frames, -1, np.int64)
        new[frames] = np.arange(len(frames))
        mk = np.flatnonzero(new[self.m_frame] >= 0)
        sk = np.flatnonzero(new[self.s_frame] >= 0)
        # keep rows grouped by frame in the new frame order
        mk = mk[np.argsort(new[self.m_frame[mk]], kind="stable")]
        sk = sk[np.argsort(new[self.s_frame[sk]], kind="stable")]
        counts = np.diff(self.gt_offsets)[frames]
        gt_rows = (np.concatenate([np.arange(self.gt_offsets[k], self.gt_offsets[k + 1])
                                   for k in frames]) if len(frames) else np.zeros(0, np.int64))
        d = {k: getattr(self, k)[mk] for k in _MERGED}
        d.update({k: getattr(self, k)[sk] for k in _SINGLE})
        d["m_frame"], d["s_frame"] = new[self.m_frame[mk]], new[self.s_frame[sk]]
        d.update({k: getattr(self, k)[frames] for k in _FRAMES if k != "gt_offsets"})
        d["gt_offsets"] = np.r_[0, np.cumsum(counts)].astype(np.int64)
        d.update({k: getattr(self, k)[gt_rows] for k in _GT})
        return MimoDataset(self.class_names, self.feature_names, info=dict(self.info), **d)

    def frames_of_groups(self, groups) -> np.ndarray:
        return np.flatnonzero(np.isin(self.frame_group, list(groups)))

    def save(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {"class_names": list(self.class_names), "feature_names": list(self.feature_names),
                "info": self.info, "version": CACHE_VERSION}
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, meta=np.array(json.dumps(meta)),
                            **{k: getattr(self, k) for k in _ALL})
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path) -> "MimoDataset":
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("version") != CACHE_VERSION:
                raise ValueError(f"{path}: cache version {meta.get('version')} != {CACHE_VERSION}")
            arrays = {k: z[k] for k in _ALL}
        return cls(tuple(meta["class_names"]), tuple(meta["feature_names"]), info=meta["info"],
                   **arrays)

    @classmethod
    def concat(cls, parts: Sequence["MimoDataset"]) -> "MimoDataset":
        if not parts:
            raise ValueError("nothing to concatenate")
        first = parts[0]
        for p in parts[1:]:
            if p.class_names != first.class_names or p.feature_names != first.feature_names:
                raise ValueError("datasets with different classes or features")
        f_off = np.cumsum([0] + [p.n_frames for p in parts])
        g_off = np.cumsum([0] + [len(p.gt_box) for p in parts])
        d = {k: np.concatenate([getattr(p, k) for p in parts]) for k in _ALL
             if k not in ("m_frame", "s_frame", "gt_offsets")}
        d["m_frame"] = np.concatenate([p.m_frame + o for p, o in zip(parts, f_off)])
        d["s_frame"] = np.concatenate([p.s_frame + o for p, o in zip(parts, f_off)])
        d["gt_offsets"] = np.concatenate([np.zeros(1, np.int64)]
                                         + [p.gt_offsets[1:] + o for p, o in zip(parts, g_off)])
        info = {"sources": [s for p in parts for s in p.info.get("sources", [])]}
        for key in ("dropped_single", "frames_without_gt", "frames_without_heads", "issues"):
            info[key] = int(sum(p.info.get(key, 0) for p in parts))
        info["settings"] = first.info.get("settings")
        return cls(first.class_names, first.feature_names, info=info, **d)

    def summary(self) -> dict:
        """Counts for manifests and reports (read from a feature table: its frame,
        single-head and ground-truth counts, None where the table has none)."""
        counts = {"frames": int(self.n_frames), "single": int(len(self.s_score)),
                  "single_tp": int((self.s_iou_class >= TP_IOU).sum()),
                  "gt_boxes": int(len(self.gt_box)), "gt_ignored": int(self.gt_ignore().sum())}
        if "table" in self.info:  # the table holds merged detections only
            counts = {k: self.info["table"].get(k) for k in counts}
        return {"groups": len(self.groups), "frames": counts["frames"], "merged": len(self),
                "merged_tp": int(self.tp.sum()), "single": counts["single"],
                "single_tp": counts["single_tp"], "gt_boxes": counts["gt_boxes"],
                "gt_ignored": counts["gt_ignored"]}


# ------------------------------------------------------------------ building
def _targets(boxes, scores, labels, gt_boxes, gt_labels):
    """(iou_class, iou_any) of detections against a frame's ground truth."""
    from lidar_quality_core.detection_eval import match_frame

    m = match_frame(boxes, scores, list(labels), gt_boxes, list(gt_labels), iou_threshold=TP_IOU)
    return m.iou_same_class, m.iou_any


def _gt_points(f, gt_ids, gt_boxes) -> np.ndarray:
    """Points of each ground-truth object: instance counts of ``/lidar/points_gt``, else
    the cloud points inside the box."""
    if f.points_gt is not None and all(i.isdigit() for i in gt_ids):
        from lidar_quality_core.pointcloud import read_fields

        inst = read_fields(f.points_gt, "instance", np.int64)[:, 0]
        counts = np.bincount(inst, minlength=1)
        ids = np.array([int(i) for i in gt_ids], np.int64)
        return np.where(ids < len(counts), counts[np.minimum(ids, len(counts) - 1)], 0)
    from lidar_quality_core.box_geometry import count_points_in_boxes
    from lidar_quality_core.pointcloud import finite_mask, xyz_intensity

    xyz, _ = xyz_intensity(f.points)
    if not len(gt_boxes):
        return np.zeros(0, np.int64)
    return count_points_in_boxes(xyz[finite_mask(xyz)], gt_boxes).astype(np.int64)


class _Builder:
    def __init__(self, settings: MimoSettings):
        self.settings = settings
        self.t = {k: [] for k in _ALL if k != "gt_offsets"}
        self.dropped_single = 0

    def add(self, f, group: str, source: str, frame, single):
        from lidar_quality_core.boxes import detections_to_arrays

        t, k = self.t, len(self.t["frame_group"])
        names = self.settings.class_names
        gt = detections_to_arrays(f.gt_objects)
        gb = gt.boxes[gt.valid].reshape(-1, 7)
        gl = [c for c, ok in zip(gt.labels, gt.valid) if ok]
        gi = [c for c, ok in zip(gt.ids, gt.valid) if ok]
        m = frame.merge
        mlab = [names[c - 1] for c in m.labels.tolist()]
        ic, ia = _targets(m.boxes, m.scores, mlab, gb, gl)
        t["X"].append(frame.features)
        t["m_box"].append(m.boxes.reshape(-1, 7))
        t["m_probs"].append(m.class_probs.reshape(len(m), 1 + len(names)))
        t["m_label"].append(m.labels.astype(np.int64))
        t["m_score"].append(m.scores)
        t["m_var"].append(m.stats.predictive_variance.reshape(-1, 7))
        t["m_iou_class"].append(ic)
        t["m_iou_any"].append(ia)
        t["m_frame"].append(np.full(len(m), k, np.int64))
        # single head: the usable boxes of head 0
        h = single
        ok = np.isfinite(h.class_scores).all(axis=1)
        self.dropped_single += int((~ok).sum())
        probs = h.class_scores[ok]
        lab = (np.argmax(probs[:, 1:], axis=1) + 1) if len(probs) else np.zeros(0, np.int64)
        score = probs[np.arange(len(probs)), lab]
        ic, ia = _targets(h.boxes[ok], score, [names[c - 1] for c in lab.tolist()], gb, gl)
        t["s_box"].append(h.boxes[ok].reshape(-1, 7))
        t["s_probs"].append(probs.reshape(-1, 1 + len(names)))
        t["s_label"].append(lab.astype(np.int64))
        t["s_score"].append(score)
        t["s_var"].append(np.asarray(h.variances, np.float64)[ok].reshape(-1, 7))
        t["s_iou_class"].append(ic)
        t["s_iou_any"].append(ia)
        t["s_frame"].append(np.full(len(probs), k, np.int64))
        t["frame_group"].append(group)
        t["frame_source"].append(source)
        t["frame_stamp"].append(int(f.stamp_ns))
        t["frame_heads"].append(len(frame.heads_used))
        t["gt_box"].append(gb)
        t["gt_label"].append(np.array(gl, dtype=str).reshape(-1))
        t["gt_id"].append(np.array(gi, dtype=str).reshape(-1))
        t["gt_points"].append(_gt_points(f, gi, gb).astype(np.int64).reshape(-1))

    def build(self, info: dict) -> MimoDataset:
        t = self.t
        C1 = 1 + len(self.settings.class_names)
        F = len(self.settings.feature_names())
        empty = {"X": (0, F), "m_box": (0, 7), "m_probs": (0, C1), "m_var": (0, 7),
                 "s_box": (0, 7), "s_probs": (0, C1), "s_var": (0, 7), "gt_box": (0, 7)}
        d = {}
        for k in _MERGED + _SINGLE + _GT:
            if t[k]:
                d[k] = np.concatenate(t[k])
            else:
                dt = str if k in ("gt_label", "gt_id") else (
                    np.int64 if k.endswith(("label", "frame", "points")) else np.float64)
                d[k] = np.zeros(empty.get(k, (0,)), dt)
        nf = len(t["frame_group"])
        d["frame_group"] = np.array(t["frame_group"], dtype=str).reshape(nf)
        d["frame_source"] = np.array(t["frame_source"], dtype=str).reshape(nf)
        d["frame_stamp"] = np.array(t["frame_stamp"], np.int64).reshape(nf)
        d["frame_heads"] = np.array(t["frame_heads"], np.int64).reshape(nf)
        d["gt_offsets"] = np.r_[0, np.cumsum([len(b) for b in t["gt_box"]])].astype(np.int64)
        info = {**info, "dropped_single": self.dropped_single,
                "settings": _settings_dict(self.settings)}
        return MimoDataset(tuple(self.settings.class_names),
                           tuple(self.settings.feature_names()), info=info, **d)


def _settings_dict(settings: MimoSettings) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(settings), default=str))


def settings_for(num_heads: int, **overrides) -> MimoSettings:
    """The dataset's settings: ``use_points=True`` (features of both models)."""
    s = MimoSettings(num_heads=int(num_heads), use_points=True, **overrides)
    s.validate()
    return s


def read_bag(bag, *, settings: MimoSettings | None = None, progress: bool = True,
             topics: dict | None = None) -> MimoDataset:
    """One perception bag -> :class:`MimoDataset` (no cache); ``topics``: its topic names by
    key (``--topic``)."""
    from lidar_quality_ros.bag_io import bag_info
    from lidar_quality_ros.perception_bag import head_count, perception_frames, topic_of
    from lidar_quality_core.progress import Progress
    from lidar_quality_ros.perception_bag import bag_group

    from mimo_ros.pipeline import frame_features, head_detections

    bag = Path(bag)
    k = head_count(bag, topics)
    if k < 1:
        raise ValueError(f"{bag}: no {topic_of('head_0', topics)} topic (not a multi-head "
                         "perception bag; name its topics with --topic head_0=TOPIC ...)")
    settings = settings or settings_for(k)
    if settings.num_heads != k:
        raise ValueError(f"{bag}: {k} heads, settings for {settings.num_heads}")
    group = bag_group(bag)
    info = bag_info(bag)
    points = topic_of("points", topics)
    total = info.topics[points].count if points in info.topics else None
    bar = Progress(f"{group}:", total, progress)
    b = _Builder(settings)
    no_gt = no_heads = issues = 0
    for f in perception_frames(bag, want=("points", "points_gt", "gt_objects"), heads=k,
                               topics=topics):
        bar.update()
        if f.gt_objects is None:
            no_gt += 1  # no targets without ground truth
            continue
        if f.heads[0] is None or all(h is None for h in f.heads):
            no_heads += 1  # no baseline without head 0
            continue
        frame = frame_features(f.heads, f.head_variances, settings, f.points)
        issues += len(frame.issues)
        single, _ = head_detections(f.heads[0], f.head_variances[0], settings)
        b.add(f, group, str(bag), frame, single)
    bar.close()
    return b.build({"sources": [{"path": str(bag), "group": group}], "frames_without_gt": no_gt,
                    "frames_without_heads": no_heads, "issues": issues})


def resolve_bags(paths: Sequence) -> list[Path]:
    """Bag directories of ``paths`` (a bag, or a directory of bags)."""
    from lidar_quality_ros.perception_bag import resolve_bags as resolve

    return resolve(paths)


def _code_hash() -> str:
    from lidar_quality_core.mimo import merging, uncertainty
    from mimo_ros import pipeline

    return source_hash(__file__, pipeline, merging, uncertainty)


def _cache_path(cache_dir, bag: Path, settings: MimoSettings, topics=None) -> Path:
    files = sorted(p for p in bag.iterdir() if p.is_file())
    fp = [[str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns] for p in files]
    payload = json.dumps({"v": CACHE_VERSION, "code": _code_hash(), "files": fp,
                          "settings": _settings_dict(settings),
                          **({"topics": topics} if topics else {})}, sort_keys=True)
    key = hashlib.sha256(payload.encode()).hexdigest()[:16]
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{bag.parent.name}_{bag.name}")
    return Path(cache_dir) / f"mimo_{safe}_{key}.npz"


def load_bags(paths: Sequence, *, cache_dir=None, progress: bool = True,
              settings: MimoSettings | None = None, topics: dict | None = None) -> MimoDataset:
    """All bags of ``paths`` (:func:`resolve_bags`) as one dataset, cached per bag;
    ``topics``: the bags' topic names by key (``--topic``)."""
    parts = []
    for bag in resolve_bags(paths):
        from lidar_quality_ros.perception_bag import head_count

        s = settings or settings_for(max(head_count(bag, topics), 1))
        p = _cache_path(cache_dir, bag, s, topics) if cache_dir is not None else None
        ds = None
        if p is not None and p.exists():
            try:
                ds = MimoDataset.load(p)
            except Exception as exc:  # a damaged cache file is rebuilt, not fatal
                if progress:
                    sys.stderr.write(f"cache {p} unreadable ({exc}); rebuilding\n")
        if ds is None:
            ds = read_bag(bag, settings=s, progress=progress, topics=topics)
            if p is not None:
                ds.save(p)
        parts.append(ds)
    return MimoDataset.concat(parts)
