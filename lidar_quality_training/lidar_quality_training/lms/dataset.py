"""LidarMetaSeg segment dataset: one row per kept segment of every frame (no rclpy).

Rows are computed with the node's own code: clouds are decoded by
:func:`lms_ros.pipeline.decode` and measured by :func:`lms_ros.pipeline.frame_metrics`,
so a model is trained on exactly the metrics the node computes online; the targets IoU and
IoU_adj come from :func:`lidar_quality_core.lms.segment_metrics.segment_targets`.

Sources (:func:`discover_sources`):

* **perception bags** (``reference-perception bag`` / ``split``): a bag directory, or a
  directory of bag directories (one sequence each, e.g. ``data/perception/meta_train``).
  Per frame the node's two-cloud input: ``/lidar/points`` (x, y, z, intensity, ring) and
  ``/perception/segmentation`` (one probability field per class, same point order);
  ``ring_from="segmentation"`` uses the segmentation cloud alone (no ring: rows from the
  vertical field of view). Labels: ``/lidar/points_gt`` ``label`` (lidar_sim class id =
  class index), same point order.
* **SemanticKITTI-style directory**: ``sequences/NN/velodyne/*.bin`` (float32 x, y, z,
  remission), ``sequences/NN/labels/*.label`` (raw SemanticKITTI ids, mapped to our
  classes by ``lidar_sim.classes.from_semantickitti``) and per-scan probabilities
  ``sequences/NN/probabilities/*.npy`` (float32 (N, classes), class order of the
  settings), under the same root or under ``probabilities_root`` (what
  ``reference-perception semantickitti --out`` writes). The arrays are packed into the
  same PointCloud2 the node receives and decoded like it.

Choices: ground truth ``ignore_label`` (default 0 = ``unlabeled``, SemanticKITTI's
convention) counts in no target; segments with SP < ``settings.min_segment_points``
(default 10, paper III-A) are excluded; a kept segment whose IoU is undefined (all its
projected pixels ignored) is dropped and counted (``info["dropped_undefined"]``).

Cross-validation groups are *sub-sequences*: each sequence is cut into disjoint blocks of
``block_frames`` consecutive frames (frame index // block_frames); every block is one
group, so a fold never separates neighbouring frames of a block (paper III-A: 10 disjoint
sub-sequences; random frames would put near-identical scans on both sides).

Each sequence is cached as ``.npz`` under ``cache_dir`` (key: source files' sizes and
mtimes, settings, ignore label, ring source, :data:`CACHE_VERSION` and
:func:`code_version`, a hash of the modules that compute the rows).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from lidar_quality_training.cache import source_hash
from lidar_quality_core.progress import Progress

__all__ = ["CACHE_VERSION", "DEFAULT_BLOCK_FRAMES", "Source", "SegmentDataset", "code_version",
           "discover_sources", "subsequence_groups", "frame_rows", "source_frames",
           "sequence_rows", "build_dataset", "load_frame"]

CACHE_VERSION = 1
DEFAULT_BLOCK_FRAMES = 10
RING_FROM = ("points", "segmentation")
_PER_ROW = ("iou", "iou_adj", "segment_class", "size", "size_projected", "sequence",
            "frame", "group")


@dataclass(frozen=True)
class Source:
    """One sequence: a perception bag, or one sequence of a SemanticKITTI-style root."""

    kind: str          # "bag" | "semantickitti"
    path: Path         # bag directory | sequences/NN directory
    name: str          # e.g. "meta_train/seq_00", "semantickitti/08"
    probabilities: Path | None = None   # semantickitti: directory of the .npy files
    topics: tuple = ()  # bag: (key, topic) pairs of ``--topic`` (perception_bag keys)

    def fingerprint(self) -> list:
        """(name, size, mtime) of the files this source reads."""
        if self.kind == "bag":
            files = sorted(p for p in self.path.iterdir() if p.is_file())
        else:
            files = sorted([*(self.path / "velodyne").glob("*.bin"),
                            *(self.path / "labels").glob("*.label"),
                            *self.probabilities.glob("*.npy")])
        return [[str(p), p.stat().st_size, p.stat().st_mtime_ns] for p in files]


def discover_sources(path, probabilities_root=None, topics=None) -> list[Source]:
    """Sources under ``path``: a bag, a directory of bags, or a SemanticKITTI-style root
    (``sequences/NN``); ``probabilities_root`` holds ``sequences/NN/probabilities``
    when the .npy files are not under ``path``; ``topics``: the bags' topic names by key
    (``--topic``)."""
    path = Path(path)
    topics = tuple(sorted((topics or {}).items()))
    if (path / "metadata.yaml").is_file():
        return [Source("bag", path, f"{path.parent.name}/{path.name}", topics=topics)]
    if (path / "sequences").is_dir():
        proot = Path(probabilities_root) if probabilities_root else path
        out = []
        for seq in sorted(p for p in (path / "sequences").iterdir() if p.is_dir()):
            if (seq / "velodyne").is_dir() and (seq / "labels").is_dir():
                prob = proot / "sequences" / seq.name / "probabilities"
                if not prob.is_dir():
                    raise FileNotFoundError(f"{seq}: no probabilities directory {prob}")
                out.append(Source("semantickitti", seq, f"{path.name}/{seq.name}", prob))
        if not out:
            raise FileNotFoundError(f"{path}: no sequences/NN with velodyne/ and labels/")
        return out
    if path.is_dir():
        bags = sorted(p for p in path.iterdir() if (p / "metadata.yaml").is_file())
        if bags:
            return [Source("bag", b, f"{path.name}/{b.name}", topics=topics) for b in bags]
    raise FileNotFoundError(f"{path}: neither a perception bag, a directory of bags nor a "
                            "SemanticKITTI-style root (sequences/NN)")


def subsequence_groups(sequence, frame, block_frames: int = DEFAULT_BLOCK_FRAMES) -> np.ndarray:
    """Group id (0, 1, ...) of each row: its sequence's block of ``block_frames``
    consecutive frames; ids are unique over sequences, in (sequence, block) order."""
    if int(block_frames) < 1:
        raise ValueError(f"block_frames must be >= 1, got {block_frames}")
    seq = np.asarray(sequence, dtype=np.int64)
    block = np.asarray(frame, dtype=np.int64) // int(block_frames)
    if seq.size == 0:
        return np.zeros(0, np.int32)
    key = seq * (int(block.max()) + 1) + block
    return np.unique(key, return_inverse=True)[1].astype(np.int32).reshape(-1)


@dataclass
class SegmentDataset:
    """Segments (rows) with their metrics ``X`` (columns ``names``) and targets.

    Per row: ``iou``, ``iou_adj``, ``segment_class`` (predicted class index), ``size``
    (S, filled pixels), ``size_projected`` (SP), ``sequence`` (index into
    ``sequences``), ``frame`` (frame index in its sequence), ``group`` (sub-sequence id).
    ``info``: how it was made (settings, counts), JSON-serialisable.
    """

    X: np.ndarray
    names: tuple[str, ...]
    iou: np.ndarray
    iou_adj: np.ndarray
    segment_class: np.ndarray
    size: np.ndarray
    size_projected: np.ndarray
    sequence: np.ndarray
    frame: np.ndarray
    group: np.ndarray
    sequences: tuple[str, ...]
    class_names: tuple[str, ...]
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.iou_adj)

    @property
    def tp(self) -> np.ndarray:
        """Meta classification target: IoU_adj > 0 (the segment is not a false positive)."""
        return self.iou_adj > 0

    @property
    def n_frames(self) -> int:
        return int(len(np.unique(np.stack([self.sequence, self.frame]), axis=1).T))

    def columns(self, names: Sequence[str]) -> np.ndarray:
        """The metric columns ``names`` (in that order)."""
        idx = {n: j for j, n in enumerate(self.names)}
        missing = [n for n in names if n not in idx]
        if missing:
            raise KeyError(f"unknown metrics {missing}")
        return self.X[:, [idx[n] for n in names]]

    def subset(self, rows) -> "SegmentDataset":
        rows = np.asarray(rows)
        kw = {k: getattr(self, k)[rows] for k in ("X",) + _PER_ROW}
        return dataclasses.replace(self, **kw)

    def regroup(self, block_frames: int) -> "SegmentDataset":
        """The same rows with groups of ``block_frames`` frames."""
        info = {**self.info, "block_frames": int(block_frames)}
        return dataclasses.replace(self, group=subsequence_groups(self.sequence, self.frame,
                                                                  block_frames), info=info)

    def save(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {"names": list(self.names), "sequences": list(self.sequences),
                "class_names": list(self.class_names), "info": self.info}
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, X=self.X, meta=np.array(json.dumps(meta)),
                            **{k: getattr(self, k) for k in _PER_ROW})
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path) -> "SegmentDataset":
        with np.load(Path(path), allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return cls(X=z["X"], names=tuple(meta["names"]), sequences=tuple(meta["sequences"]),
                       class_names=tuple(meta["class_names"]), info=meta["info"],
                       **{k: z[k] for k in _PER_ROW})

    @classmethod
    def concat(cls, parts: Sequence["SegmentDataset"],
               block_frames: int = DEFAULT_BLOCK_FRAMES) -> "SegmentDataset":
        """Rows of all parts; sequences renumbered in part order, groups recomputed."""
        if not parts:
            raise ValueError("no data")
        names, cn = parts[0].names, parts[0].class_names
        for p in parts[1:]:
            if p.names != names or p.class_names != cn:
                raise ValueError("parts have different metric schemas")
        seqs, seq_idx = [], []
        for p in parts:
            seq_idx.append(p.sequence + len(seqs))
            seqs.extend(p.sequences)
        sequence = np.concatenate(seq_idx).astype(np.int32)
        frame = np.concatenate([p.frame for p in parts]).astype(np.int32)
        cat = {k: np.concatenate([getattr(p, k) for p in parts])
               for k in ("iou", "iou_adj", "segment_class", "size", "size_projected")}
        info = {k: v for k, v in parts[0].info.items()
                if k not in ("n_frames", "n_segments", "dropped_undefined", "n_excluded",
                             "source")}
        info.update(block_frames=int(block_frames),
                    n_frames=int(sum(p.info.get("n_frames", 0) for p in parts)),
                    n_excluded=int(sum(p.info.get("n_excluded", 0) for p in parts)),
                    dropped_undefined=int(sum(p.info.get("dropped_undefined", 0)
                                              for p in parts)),
                    sources=[s for p in parts for s in p.info.get("sources", [p.info.get("source")])])
        return cls(X=np.concatenate([p.X for p in parts]), names=names, **cat,
                   sequence=sequence, frame=frame,
                   group=subsequence_groups(sequence, frame, block_frames),
                   sequences=tuple(seqs), class_names=cn, info=info)


# -- frames ----------------------------------------------------------------------------


def _settings(settings):
    from lms_ros.pipeline import LmsSettings

    s = LmsSettings() if settings is None else settings
    s.validate()
    return s


def _gt_labels(msg) -> np.ndarray:
    from lidar_quality_core.pointcloud import read_fields

    return read_fields(msg, ["label"], dtype=np.int64)[:, 0]


def source_frames(source: Source, settings=None, *, ring_from: str = "points",
                  frames: Sequence[int] | None = None) -> Iterator[tuple[int, object, np.ndarray]]:
    """``(frame index, LmsInput, ground-truth class per point)`` of each frame of
    ``source`` (only ``frames`` if given), decoded by the node's
    :func:`lms_ros.pipeline.decode`."""
    from lms_ros.pipeline import decode

    settings = _settings(settings)
    if ring_from not in RING_FROM:
        raise ValueError(f"ring_from must be one of {RING_FROM}, got {ring_from!r}")
    wanted = None if frames is None else set(int(i) for i in frames)
    if source.kind == "bag":
        from lidar_quality_ros.perception_bag import perception_frames

        want = ("segmentation", "points_gt") + (("points",) if ring_from == "points" else ())
        for f in perception_frames(source.path, want=want, require="segmentation",
                                   topics=dict(source.topics)):
            if wanted is not None and f.index not in wanted:
                if f.index > max(wanted):
                    return
                continue
            if f.points_gt is None:
                raise ValueError(f"{source.name} frame {f.index}: no /lidar/points_gt")
            if ring_from == "points":
                if f.points is None:
                    raise ValueError(f"{source.name} frame {f.index}: no /lidar/points")
                inp = decode(f.points, settings, probabilities_msg=f.segmentation)
            else:
                inp = decode(f.segmentation, settings)
            yield f.index, inp, _gt_labels(f.points_gt)
        return
    from lidar_sim.classes import from_semantickitti
    from reference_perception.messages import probability_cloud
    from std_msgs.msg import Header

    for scan in sorted((source.path / "velodyne").glob("*.bin")):
        idx = int(scan.stem)
        if wanted is not None and idx not in wanted:
            continue
        pts = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
        raw = np.fromfile(source.path / "labels" / f"{scan.stem}.label", dtype="<u4")
        probs = np.load(source.probabilities / f"{scan.stem}.npy")
        if len(raw) != len(pts) or len(probs) != len(pts):
            raise ValueError(f"{scan}: {len(pts)} points, {len(raw)} labels, "
                             f"{len(probs)} probability rows")
        if probs.ndim != 2 or probs.shape[1] != len(settings.class_names):
            raise ValueError(f"{scan}: probabilities {probs.shape}, expected "
                             f"(N, {len(settings.class_names)})")
        msg = probability_cloud(Header(frame_id="lidar"), pts[:, :3], pts[:, 3], probs,
                                settings.class_names)
        yield idx, decode(msg, settings), from_semantickitti(raw).astype(np.int64)


def frame_rows(inp, gt_labels, settings=None, *, ignore_label: int | None = 0):
    """``(SegmentResult, iou, iou_adj, keep)`` of one decoded frame: the node's metrics
    (:func:`lms_ros.pipeline.frame_metrics`) and the targets of its kept segments; ``keep``
    marks the rows with a defined IoU."""
    from lms_ros.pipeline import frame_metrics
    from lidar_quality_core.lms.targets import segment_targets

    settings = _settings(settings)
    res = frame_metrics(inp, settings)
    iou, iou_adj = segment_targets(res, gt_labels, ignore_label=ignore_label)
    return res, iou, iou_adj, np.isfinite(iou_adj)


def sequence_rows(source: Source, settings=None, *, ignore_label: int | None = 0,
                  ring_from: str = "points", progress=None) -> SegmentDataset:
    """All kept segments of one sequence (``sequence`` = 0, groups of one frame each:
    :meth:`SegmentDataset.concat` sets the real ones)."""
    settings = _settings(settings)
    names = tuple(settings.metric_names())
    parts = {k: [] for k in ("X", "iou", "iou_adj", "cls", "S", "SP", "frame")}
    n_frames = n_undefined = n_excluded = 0
    for idx, inp, gt in source_frames(source, settings, ring_from=ring_from):
        res, iou, iou_adj, ok = frame_rows(inp, gt, settings, ignore_label=ignore_label)
        kid = res.kept_ids[ok]
        parts["X"].append(res.features[ok])
        parts["iou"].append(iou[ok])
        parts["iou_adj"].append(iou_adj[ok])
        parts["cls"].append(res.segment_class[kid])
        parts["S"].append(res.size[kid])
        parts["SP"].append(res.size_projected[kid])
        parts["frame"].append(np.full(len(kid), idx, np.int32))
        n_frames += 1
        n_undefined += int((~ok).sum())
        n_excluded += res.n_segments - len(res.kept_ids)
        if progress is not None:
            progress(n_frames)
    if not n_frames:
        raise ValueError(f"{source.name}: no frames")
    frame = np.concatenate(parts["frame"])
    info = {"settings": _settings_dict(settings), "ignore_label": ignore_label,
            "ring_from": ring_from if source.kind == "bag" else "none",
            "n_frames": n_frames, "n_excluded": int(n_excluded),
            "dropped_undefined": int(n_undefined), "source": str(source.path),
            "cache_version": CACHE_VERSION}
    return SegmentDataset(
        X=np.concatenate(parts["X"]).reshape(-1, len(names)), names=names,
        iou=np.concatenate(parts["iou"]), iou_adj=np.concatenate(parts["iou_adj"]),
        segment_class=np.concatenate(parts["cls"]).astype(np.int32),
        size=np.concatenate(parts["S"]).astype(np.int64),
        size_projected=np.concatenate(parts["SP"]).astype(np.int64),
        sequence=np.zeros(len(frame), np.int32), frame=frame, group=frame.copy(),
        sequences=(source.name,), class_names=tuple(settings.class_names), info=info)


def _settings_dict(settings) -> dict:
    d = dataclasses.asdict(settings)
    return json.loads(json.dumps(d, default=lambda o: list(o) if isinstance(o, tuple) else str(o)))


def code_version() -> str:
    """Short hash of the sources that compute the rows (part of the cache key): a change
    to the decoding, projection, fill or metrics invalidates the cache."""
    from lidar_quality_core import pointcloud
    from lidar_quality_core.lms import fill, projection, segment_metrics
    from lms_ros import pipeline

    return source_hash(__file__, pipeline, segment_metrics, projection, fill, pointcloud)


def _cache_path(cache_dir: Path, source: Source, settings, ignore_label, ring_from) -> Path:
    key = json.dumps({"v": CACHE_VERSION, "code": code_version(),
                      "source": source.fingerprint(),
                      "settings": _settings_dict(settings), "ignore": ignore_label,
                      "ring_from": ring_from if source.kind == "bag" else "none",
                      **({"topics": source.topics} if source.topics else {})},
                     sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return Path(cache_dir) / f"{source.name.replace('/', '_')}-{digest}.npz"


def _frame_count(source: Source) -> int:
    if source.kind == "bag":
        from lidar_quality_ros.bag_io import bag_info
        from lidar_quality_ros.perception_bag import topic_of

        t = bag_info(source.path).topics.get(topic_of("segmentation", dict(source.topics)))
        return t.count if t else 0
    return len(list((source.path / "velodyne").glob("*.bin")))


def build_dataset(paths, settings=None, *, probabilities_root=None,
                  ignore_label: int | None = 0, ring_from: str = "points",
                  block_frames: int = DEFAULT_BLOCK_FRAMES, cache_dir=None,
                  quiet: bool = False, topics: dict | None = None) -> SegmentDataset:
    """The segment dataset of every sequence under ``paths`` (see :func:`discover_sources`;
    ``topics``: the bags' topic names by key), each sequence read from / written to the
    ``.npz`` cache in ``cache_dir`` if given."""
    settings = _settings(settings)
    if isinstance(paths, (str, Path)):
        paths = [paths]
    sources = [s for p in paths for s in discover_sources(p, probabilities_root, topics)]
    parts = []
    for k, src in enumerate(sources):
        cpath = (_cache_path(cache_dir, src, settings, ignore_label, ring_from)
                 if cache_dir else None)
        if cpath is not None and cpath.is_file():
            part = SegmentDataset.load(cpath)
            if not quiet:
                sys.stderr.write(f"{src.name}: {len(part)} segments (cached {cpath.name})\n")
        else:
            bar = Progress(f"[{k + 1}/{len(sources)}] {src.name}", _frame_count(src), not quiet)
            part = sequence_rows(src, settings, ignore_label=ignore_label,
                                 ring_from=ring_from, progress=bar)
            if cpath is not None:
                part.save(cpath)
        parts.append(part)
    return SegmentDataset.concat(parts, block_frames)


def load_frame(source: Source, index: int, settings=None, *, ignore_label: int | None = 0,
               ring_from: str = "points"):
    """``(LmsInput, gt labels, SegmentResult, iou, iou_adj)`` of one frame (for figures)."""
    for idx, inp, gt in source_frames(source, settings, ring_from=ring_from, frames=[index]):
        res, iou, iou_adj, _ = frame_rows(inp, gt, settings, ignore_label=ignore_label)
        return inp, gt, res, iou, iou_adj
    raise IndexError(f"{source.name}: no frame {index}")
