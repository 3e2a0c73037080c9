"""LMD feature datasets: one row per scored detection, with its features and targets.

Sources (each frame goes through :func:`lmd_ros.pipeline.frame_features`, the node's own
conversion and features, so a model learns exactly what the node computes):

* perception bags (``lidar_quality_ros.perception_bag.perception_frames``): cloud,
  post-NMS detections, pre-NMS proposals and the ground truth ``/lidar/gt_objects`` per
  stamp; one group (sequence) per bag;
* a KITTI object directory (``<root>/<split>/velodyne/*.bin``, ``label_2/*.txt``,
  ``calib/*.txt``) plus detector result files (KITTI result format: a label line with a
  16th column, the score; e.g. ``reference-perception kitti``) and, for the proposal
  modes, one proposal file per frame in the same format (pre-NMS boxes). Result and
  proposal boxes become Detection3DArray messages, the scan a PointCloud2, and then take
  the same path as bag frames. Group = the first ``group_digits`` characters of the frame
  id (``lidar-sim`` writes ``SSFFFF``: sequence, frame). Every file is read with its
  frame's own calibration: labels with ``<split>/calib/<id>.txt`` (required: without it
  camera-frame boxes cannot be placed), result / proposal files with the
  ``calib/<id>.txt`` written beside them if there is one (our writers record the
  calibration they used), else with the dataset's.

Rows: valid scored boxes only (the pipeline's invalid boxes, e.g. NaN values or a class
outside ``class_names``, have no features; they are counted in ``info["dropped_invalid"]``).
Targets: ``iou_any`` = IoU_BEV with the best ground-truth box of any class (the authors'),
``iou_class`` = with the best one of the detection's class (``class_aware=True``); TP iff
IoU_BEV >= 0.5 (:data:`TP_IOU`). Both come from ``detection_eval.match_frame``. The frame
table keeps each frame's source and ground truth (boxes, classes, ids, points inside), so
targets against other labels (annotation errors) need no second pass over the data.

Caching: one ``.npz`` per source (bag or KITTI directory) and mode under ``cache_dir``,
named by a key over the source files (path, size, mtime), the settings and the code of
this module, ``features`` and ``pipeline``; a changed input or code builds anew.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from lidar_quality_training.cache import source_hash
from lidar_quality_core.conventions import TP_IOU
from lidar_quality_core.intensity import INTENSITY_SCALES, IntensityScale
from lidar_quality_core.progress import Progress
from lidar_quality_ros.perception_bag import add_topic_option, bag_group, resolve_bags

__all__ = ["TP_IOU", "KITTI_TYPES", "LmdDataset", "Progress", "resolve_bags", "bag_group",
           "load_bags", "load_kitti", "dataset_from_messages",
           "read_kitti_objects", "read_calib", "frame_calib",
           "kitti_to_lidar",
           "settings_for", "add_source_args", "settings_from_args", "load_from_args"]

CACHE_VERSION = 1
#: KITTI object types -> our class names (lidar-sim writes vans of class truck as "Van").
#: DontCare regions are skipped; other types keep their lower-case name (outside the
#: models' class_names they are invalid detections, but count as ground truth).
KITTI_TYPES = {"Car": "car", "Van": "truck", "Truck": "truck", "Pedestrian": "pedestrian",
               "Person_sitting": "pedestrian", "Cyclist": "cyclist"}


# ---------------------------------------------------------------------------- dataset
_ROW = ("X", "iou_any", "iou_class", "score", "label", "box", "det_index", "det_id", "frame")
_FRAME = ("frame_group", "frame_source", "frame_key", "frame_points", "gt_offsets", "gt_box",
          "gt_label", "gt_id", "gt_points")


@dataclass
class LmdDataset:
    """Feature rows of one proposal mode plus the frame table (see module docstring)."""

    mode: str
    feature_names: tuple
    X: np.ndarray             # (n, F) float64
    iou_any: np.ndarray       # (n,) IoU_BEV with the best GT box, any class
    iou_class: np.ndarray     # (n,) IoU_BEV with the best GT box of the detection's class
    score: np.ndarray         # (n,) detector score
    label: np.ndarray         # (n,) str class name
    box: np.ndarray           # (n, 7) x, y, z, l, w, h, yaw
    det_index: np.ndarray     # (n,) position among the frame's scored boxes (output order)
    det_id: np.ndarray        # (n,) str detection id
    frame: np.ndarray         # (n,) row of the frame table
    frame_group: np.ndarray   # (f,) str group (sequence) of each frame
    frame_source: np.ndarray  # (f,) str bag directory or velodyne .bin file
    frame_key: np.ndarray     # (f,) str header stamp [ns] (bags) or frame id (KITTI)
    frame_points: np.ndarray  # (f,) int finite points of the cloud
    gt_offsets: np.ndarray    # (f + 1,) GT rows of frame k: gt_offsets[k]:gt_offsets[k+1]
    gt_box: np.ndarray        # (g, 7)
    gt_label: np.ndarray      # (g,) str
    gt_id: np.ndarray         # (g,) str
    gt_points: np.ndarray     # (g,) int cloud points inside the GT box
    class_aware: bool = False
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.score)

    @property
    def n_frames(self) -> int:
        return len(self.frame_group)

    @property
    def iou(self) -> np.ndarray:
        """The regression target: IoU_BEV with the best GT box (class-aware if set)."""
        return self.iou_class if self.class_aware else self.iou_any

    @property
    def tp(self) -> np.ndarray:
        """The classification target (bool): IoU_BEV >= 0.5."""
        return self.iou >= TP_IOU

    @property
    def group(self) -> np.ndarray:
        """(n,) group of each row."""
        return self.frame_group[self.frame]

    @property
    def distance(self) -> np.ndarray:
        """(n,) BEV distance of the box centre from the sensor."""
        return np.hypot(self.box[:, 0], self.box[:, 1])

    @property
    def groups(self) -> list[str]:
        """Distinct groups in first-seen order."""
        return list(dict.fromkeys(self.frame_group.tolist()))

    def columns(self, names: Sequence[str]) -> np.ndarray:
        """The feature columns ``names`` (in that order)."""
        pos = {n: k for k, n in enumerate(self.feature_names)}
        missing = [n for n in names if n not in pos]
        if missing:
            raise KeyError(f"features not in the dataset: {missing}")
        return self.X[:, [pos[n] for n in names]]

    def gt_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(boxes, labels, ids) of frame ``k``'s ground truth."""
        a, b = self.gt_offsets[k], self.gt_offsets[k + 1]
        return self.gt_box[a:b], self.gt_label[a:b], self.gt_id[a:b]

    def with_class_aware(self, class_aware: bool) -> "LmdDataset":
        return dataclasses.replace(self, class_aware=bool(class_aware))

    def save(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: getattr(self, k) for k in _ROW + _FRAME}
        meta = {"mode": self.mode, "feature_names": list(self.feature_names),
                "class_aware": self.class_aware, "info": self.info, "version": CACHE_VERSION}
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **arrays)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path) -> "LmdDataset":
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in _ROW + _FRAME}
        return cls(mode=meta["mode"], feature_names=tuple(meta["feature_names"]),
                   class_aware=meta["class_aware"], info=meta["info"], **arrays)

    @classmethod
    def concat(cls, parts: Sequence["LmdDataset"]) -> "LmdDataset":
        """One dataset of ``parts`` (same mode and features); frame rows renumbered."""
        if not parts:
            raise ValueError("nothing to concatenate")
        first = parts[0]
        for p in parts[1:]:
            if p.mode != first.mode or tuple(p.feature_names) != tuple(first.feature_names):
                raise ValueError("datasets of different modes / feature schemas")
        frame_off = np.cumsum([0] + [p.n_frames for p in parts])
        gt_off = np.cumsum([0] + [len(p.gt_box) for p in parts])
        cat = {k: np.concatenate([getattr(p, k) for p in parts])
               for k in _ROW + _FRAME if k not in ("frame", "gt_offsets")}
        cat["frame"] = np.concatenate([p.frame + o for p, o in zip(parts, frame_off)])
        cat["gt_offsets"] = np.concatenate(
            [np.zeros(1, np.int64)] + [p.gt_offsets[1:] + o for p, o in zip(parts, gt_off)])
        info = {"sources": [s for p in parts for s in p.info.get("sources", [])],
                "dropped_invalid": int(sum(p.info.get("dropped_invalid", 0) for p in parts)),
                "frames_without_gt": int(sum(p.info.get("frames_without_gt", 0) for p in parts)),
                "settings": first.info.get("settings")}
        return cls(mode=first.mode, feature_names=tuple(first.feature_names),
                   class_aware=first.class_aware, info=info, **cat)

    def summary(self) -> dict:
        """Counts for manifests and reports (read from a feature table: its frame and
        ground-truth counts, None where the table has none)."""
        counts = {"frames": int(self.n_frames), "gt_boxes": int(len(self.gt_box))}
        if "table" in self.info:  # the table holds no frame or ground-truth table
            counts = {k: self.info["table"].get(k) for k in counts}
        return {"groups": len(self.groups), "frames": counts["frames"], "boxes": len(self),
                "tp": int(self.tp.sum()), "tp_rate": float(self.tp.mean()) if len(self) else
                float("nan"), "gt_boxes": counts["gt_boxes"],
                "dropped_invalid": int(self.info.get("dropped_invalid", 0))}


class _Builder:
    """Collects the rows and frames of one source for one mode."""

    def __init__(self, settings):
        self.settings = settings
        self.rows: dict[str, list] = {k: [] for k in _ROW}
        self.frames: dict[str, list] = {k: [] for k in _FRAME if k != "gt_offsets"}
        self.dropped = 0

    def add(self, lmd_frame, group, source, key, gt_boxes, gt_labels, gt_ids, gt_points):
        from lidar_quality_core.detection_eval import match_frame

        k = len(self.frames["frame_group"])
        d = lmd_frame.detections
        idx = np.flatnonzero(lmd_frame.valid)
        self.dropped += len(d) - len(idx)
        labels = [d.labels[i] for i in idx.tolist()]
        m = match_frame(d.boxes[idx], d.scores[idx], labels, gt_boxes, list(gt_labels),
                        iou_threshold=TP_IOU)
        r = self.rows
        r["X"].append(lmd_frame.features[idx])
        r["iou_any"].append(m.iou_any)
        r["iou_class"].append(m.iou_same_class)
        r["score"].append(d.scores[idx])
        r["label"].append(np.array(labels, dtype=str).reshape(-1))
        r["box"].append(d.boxes[idx].reshape(-1, 7))
        r["det_index"].append(idx.astype(np.int64))
        r["det_id"].append(np.array([d.ids[i] for i in idx.tolist()], dtype=str).reshape(-1))
        r["frame"].append(np.full(len(idx), k, dtype=np.int64))
        f = self.frames
        f["frame_group"].append(group)
        f["frame_source"].append(str(source))
        f["frame_key"].append(str(key))
        f["frame_points"].append(int(lmd_frame.n_points))
        f["gt_box"].append(np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 7))
        f["gt_label"].append(np.array(list(gt_labels), dtype=str).reshape(-1))
        f["gt_id"].append(np.array(list(gt_ids), dtype=str).reshape(-1))
        f["gt_points"].append(np.asarray(gt_points, dtype=np.int64).reshape(-1))

    def build(self, info: dict) -> LmdDataset:
        names = self.settings.feature_names()
        r, f = self.rows, self.frames

        def cat(parts, empty):
            return np.concatenate(parts) if parts else empty

        nf = len(f["frame_group"])
        gt_counts = [len(b) for b in f["gt_box"]]
        arrays = dict(
            X=cat(r["X"], np.zeros((0, len(names)))), iou_any=cat(r["iou_any"], np.zeros(0)),
            iou_class=cat(r["iou_class"], np.zeros(0)), score=cat(r["score"], np.zeros(0)),
            label=cat(r["label"], np.zeros(0, dtype=str)), box=cat(r["box"], np.zeros((0, 7))),
            det_index=cat(r["det_index"], np.zeros(0, np.int64)),
            det_id=cat(r["det_id"], np.zeros(0, dtype=str)),
            frame=cat(r["frame"], np.zeros(0, np.int64)),
            frame_group=np.array(f["frame_group"], dtype=str).reshape(nf),
            frame_source=np.array(f["frame_source"], dtype=str).reshape(nf),
            frame_key=np.array(f["frame_key"], dtype=str).reshape(nf),
            frame_points=np.array(f["frame_points"], dtype=np.int64).reshape(nf),
            gt_offsets=np.concatenate([[0], np.cumsum(gt_counts)]).astype(np.int64),
            gt_box=cat(f["gt_box"], np.zeros((0, 7))),
            gt_label=cat(f["gt_label"], np.zeros(0, dtype=str)),
            gt_id=cat(f["gt_id"], np.zeros(0, dtype=str)),
            gt_points=cat(f["gt_points"], np.zeros(0, np.int64)))
        # JSON-normal (lists, not tuples): equal before and after a save / load
        info = json.loads(json.dumps({**info, "dropped_invalid": self.dropped,
                                      "settings": dataclasses.asdict(self.settings)}))
        return LmdDataset(mode=self.settings.proposal_mode, feature_names=tuple(names),
                          info=info, **arrays)


def settings_for(mode: str, **overrides):
    """``LmdSettings`` of ``mode`` with ``overrides`` (validated)."""
    from lmd_ros.pipeline import LmdSettings

    s = LmdSettings(proposal_mode=mode, **overrides)
    s.validate()
    return s


def _gt_points(cloud_msg, gt_boxes) -> np.ndarray:
    from lidar_quality_core.box_geometry import count_points_in_boxes
    from lidar_quality_core.pointcloud import finite_mask, xyz_intensity

    xyz, _ = xyz_intensity(cloud_msg)
    if not len(gt_boxes):
        return np.zeros(0, np.int64)
    return count_points_in_boxes(xyz[finite_mask(xyz)], gt_boxes).astype(np.int64)


def _modes_of(settings_list) -> list[str]:
    modes = [s.proposal_mode for s in settings_list]
    if len(set(modes)) != len(modes):
        raise ValueError(f"one settings object per mode, got modes {modes}")
    return modes


# ---------------------------------------------------------------------------- caching
def _code_hash() -> str:
    from lidar_quality_core.lmd import features
    from lmd_ros import pipeline

    return source_hash(__file__, features, pipeline)


def _fingerprint(files: Iterable[Path]) -> list:
    out = []
    for p in sorted(Path(f) for f in files):
        st = p.stat()
        out.append([str(p.resolve()), st.st_size, st.st_mtime_ns])
    return out


def _cache_file(cache_dir, name: str, settings, source_key: dict) -> Path:
    payload = json.dumps({"v": CACHE_VERSION, "code": _code_hash(), "source": source_key,
                          "settings": dataclasses.asdict(settings)}, sort_keys=True, default=str)
    key = hashlib.sha256(payload.encode()).hexdigest()[:16]
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
    return Path(cache_dir) / f"{safe}_{settings.proposal_mode}_{key}.npz"


def _cached(cache_dir, name, settings_list, source_key, build, progress):
    """{mode: dataset} from the cache where possible; ``build(missing settings)`` else."""
    out, missing = {}, []
    paths = {}
    for s in settings_list:
        if cache_dir is not None:
            p = paths[s.proposal_mode] = _cache_file(cache_dir, name, s, source_key)
            if p.exists():
                try:
                    out[s.proposal_mode] = LmdDataset.load(p)
                    continue
                except Exception as exc:  # a damaged cache file is rebuilt, not fatal
                    if progress:
                        sys.stderr.write(f"cache {p} unreadable ({exc}); rebuilding\n")
        missing.append(s)
    if missing:
        built = build(missing)
        for s in missing:
            ds = built[s.proposal_mode]
            if cache_dir is not None:
                ds.save(paths[s.proposal_mode])
            out[s.proposal_mode] = ds
    return out


# ---------------------------------------------------------------------------- bags
def _read_bag(bag: Path, settings_list, topics, progress: bool) -> dict:
    from lidar_quality_core.boxes import detections_to_arrays
    from lidar_quality_ros.bag_io import bag_info
    from lidar_quality_ros.perception_bag import DEFAULT_TOPICS, perception_frames

    from lmd_ros.pipeline import frame_features

    names = {**DEFAULT_TOPICS, **(topics or {})}
    modes = _modes_of(settings_list)
    want = ["points", "gt_objects"]
    if any(m != "exact" for m in modes):
        want.append("detections")
    if any(m != "none" for m in modes):
        want.append("proposals")
    info = bag_info(bag)
    total = info.topics[names["points"]].count if names["points"] in info.topics else None
    builders = {s.proposal_mode: _Builder(s) for s in settings_list}
    # one intensity scale per bag and mode: auto decides over the bag's first frames
    scales = {s.proposal_mode: IntensityScale(s.intensity_scale) for s in settings_list}
    no_gt = 0
    group = bag_group(bag)
    bar = Progress(f"{group}:", total, progress)
    for f in perception_frames(bag, want=tuple(want), topics=topics):
        bar.update()
        if f.gt_objects is None:
            no_gt += 1  # no targets without ground truth
            continue
        for k in want[2:]:
            if getattr(f, k) is None:
                raise ValueError(f"{bag}: frame at stamp {f.stamp_ns} has no {names[k]} "
                                 f"(needed by modes {modes})")
        gt = detections_to_arrays(f.gt_objects)
        gt_boxes = gt.boxes[gt.valid]
        gt_labels = [c for c, ok in zip(gt.labels, gt.valid) if ok]
        gt_ids = [c for c, ok in zip(gt.ids, gt.valid) if ok]
        gt_pts = _gt_points(f.points, gt_boxes)
        for s in settings_list:
            fr = frame_features(f.points, None if s.proposal_mode == "exact" else f.detections,
                                None if s.proposal_mode == "none" else f.proposals, s,
                                intensity=scales[s.proposal_mode])
            builders[s.proposal_mode].add(fr, group, bag, f.stamp_ns, gt_boxes, gt_labels,
                                          gt_ids, gt_pts)
    bar.close()
    src = {"kind": "perception_bag", "path": str(bag), "group": group}
    return {m: b.build({"sources": [src], "frames_without_gt": no_gt})
            for m, b in builders.items()}


def load_bags(bags: Sequence, settings_list, *, cache_dir=None, class_aware: bool = False,
              topics: dict | None = None, progress: bool = True) -> dict[str, LmdDataset]:
    """``{mode: LmdDataset}`` of the perception bags ``bags`` (see :func:`resolve_bags`),
    one frame pass per bag for all modes, cached per bag and mode."""
    settings_list = list(settings_list)
    _modes_of(settings_list)
    parts: dict[str, list] = {s.proposal_mode: [] for s in settings_list}
    for bag in resolve_bags(bags):
        files = [p for p in bag.iterdir() if p.is_file()]
        key = {"kind": "perception_bag", "files": _fingerprint(files), "topics": topics or {}}
        got = _cached(cache_dir, bag_group(bag), settings_list, key,
                      lambda miss, bag=bag: _read_bag(bag, miss, topics, progress), progress)
        for m, ds in got.items():
            parts[m].append(ds)
    return {m: LmdDataset.concat(p).with_class_aware(class_aware) for m, p in parts.items()}


# ---------------------------------------------------------------------------- KITTI
def read_calib(path):
    """A KITTI object calibration file as a ``lidar_sim.kitti.Calibration``."""
    from lidar_sim.kitti import Calibration

    return Calibration.from_file(path)


def frame_calib(directory, fid: str, fallback=None):
    """The calibration ``<directory>/calib/<fid>.txt``; ``fallback`` when there is none
    (no fallback: FileNotFoundError naming the file)."""
    from lidar_sim.kitti import calib_path

    path = calib_path(directory, fid)
    if path.exists():
        return read_calib(path)
    if fallback is None:
        raise _no_calib(path)
    return fallback


def _no_calib(path, more: int = 0) -> FileNotFoundError:
    return FileNotFoundError(f"{path}{f' (and {more} more frames)' if more else ''}: no "
                             f"calibration file; KITTI boxes are in the camera frame and "
                             f"cannot be placed in the lidar frame without the frame's own "
                             f"calibration")


def kitti_to_lidar(hwl_xyz_ry: np.ndarray, calib) -> np.ndarray:
    """KITTI camera boxes (N, 7: h, w, l, x, y, z bottom centre, rotation_y) -> lidar
    boxes (N, 7: x, y, z centre, l, w, h, yaw) with the frame's ``calib``; inverse of
    ``lidar_sim.kitti.label_lines``."""
    from lidar_sim.kitti import lidar_boxes

    return lidar_boxes(hwl_xyz_ry, calib)


def read_kitti_objects(path, calib, *, with_score: bool = False):
    """(lidar boxes (N, 7), class names, scores or None) of a KITTI label / result file.

    ``calib``: the frame's ``lidar_sim.kitti.Calibration`` (:func:`frame_calib`).
    DontCare lines are skipped; types map through :data:`KITTI_TYPES`. ``with_score``:
    the 16th column is the score (result format); a missing score is an error.
    """
    from lidar_sim.kitti import Calibration

    if not isinstance(calib, Calibration):
        raise TypeError(f"{path}: calib must be the frame's lidar_sim.kitti.Calibration, "
                        f"got {type(calib).__name__}")
    rows, names, scores = [], [], []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        parts = line.split()
        if not parts or parts[0] == "DontCare":
            continue
        if len(parts) < 15 or (with_score and len(parts) < 16):
            raise ValueError(f"{path}:{n}: expected {16 if with_score else 15} columns, "
                             f"got {len(parts)}")
        rows.append([float(v) for v in parts[8:15]])
        names.append(KITTI_TYPES.get(parts[0], parts[0].lower()))
        if with_score:
            scores.append(float(parts[15]))
    boxes = kitti_to_lidar(np.array(rows).reshape(-1, 7), calib)
    return boxes, names, (np.array(scores) if with_score else None)


def _kitti_ids(root: Path, split: str, results: Path, frames) -> list[str]:
    if frames is not None:
        if isinstance(frames, (str, Path)) and Path(frames).exists():
            return [s.strip() for s in Path(frames).read_text().split() if s.strip()]
        return [str(f) for f in frames]
    have = {p.stem for p in (root / split / "velodyne").glob("*.bin")}
    return sorted(p.stem for p in Path(results).glob("*.txt") if p.stem in have)


def _kitti_messages(fid: str, k: int, root: Path, split: str, results: Path, proposals):
    from lidar_quality_core.boxes import arrays_to_detections
    from lidar_quality_core.pointcloud import create_xyz_cloud
    from std_msgs.msg import Header

    base = root / split
    scan = np.fromfile(base / "velodyne" / f"{fid}.bin", dtype="<f4").reshape(-1, 4)
    calib = frame_calib(base, fid)
    gt_boxes, gt_names, _ = read_kitti_objects(base / "label_2" / f"{fid}.txt", calib)
    header = Header(frame_id="velodyne")
    header.stamp.sec = k  # frames are matched by stamp in the node; here only by position
    cloud = create_xyz_cloud(header, scan[:, :3], scan[:, 3])

    def dets(path, prefix):
        b, names, sc = read_kitti_objects(path, frame_calib(path.parent, fid, calib),
                                          with_score=True)
        return arrays_to_detections(header, b, names, sc,
                                    ids=[f"{prefix}{i}" for i in range(len(b))])

    det_msg = dets(Path(results) / f"{fid}.txt", "")
    prop_msg = None
    if proposals is not None:
        pf = Path(proposals) / f"{fid}.txt"
        if not pf.exists():
            raise FileNotFoundError(f"{pf}: no proposal file for frame {fid}")
        prop_msg = dets(pf, "p")
    return cloud, det_msg, prop_msg, gt_boxes, gt_names


def _read_kitti(root, split, results, proposals, ids, settings_list, group_digits, progress):
    from lmd_ros.pipeline import frame_features

    builders = {s.proposal_mode: _Builder(s) for s in settings_list}
    scales = {s.proposal_mode: IntensityScale(s.intensity_scale) for s in settings_list}
    bar = Progress(f"KITTI {Path(root).name}/{split}:", len(ids), progress)
    for k, fid in enumerate(ids):
        cloud, det_msg, prop_msg, gt_boxes, gt_names = _kitti_messages(
            fid, k, Path(root), split, results, proposals)
        gt_pts = _gt_points(cloud, gt_boxes)
        gt_ids = [str(j) for j in range(len(gt_boxes))]
        group = fid[:group_digits] if group_digits > 0 else fid
        src = Path(root) / split / "velodyne" / f"{fid}.bin"
        for s in settings_list:
            fr = frame_features(cloud, None if s.proposal_mode == "exact" else det_msg,
                                None if s.proposal_mode == "none" else prop_msg, s,
                                intensity=scales[s.proposal_mode])
            builders[s.proposal_mode].add(fr, group, src, fid, gt_boxes, gt_names, gt_ids,
                                          gt_pts)
        bar.update()
    bar.close()
    src = {"kind": "kitti", "path": str(root), "split": split, "results": str(results),
           "proposals": None if proposals is None else str(proposals)}
    return {m: b.build({"sources": [src], "frames_without_gt": 0}) for m, b in builders.items()}


def dataset_from_messages(frames, settings_list, *, source: dict,
                          progress: bool = False) -> dict[str, "LmdDataset"]:
    """``{mode: dataset}`` of in-memory frames (e.g. a simulation run without a bag):
    ``frames`` yields ``(cloud, detections, proposals, gt_boxes, gt_labels, gt_ids, group,
    key)`` messages and arrays; features by the node's own ``frame_features`` as for bags;
    ``source``: the dict the datasets' ``info["sources"]`` records."""
    from lmd_ros.pipeline import frame_features

    builders = {s.proposal_mode: _Builder(s) for s in settings_list}
    scales = {s.proposal_mode: IntensityScale(s.intensity_scale) for s in settings_list}
    bar = Progress(f"{source.get('path', 'frames')}:", None, progress)
    for cloud, det_msg, prop_msg, gt_boxes, gt_labels, gt_ids, group, key in frames:
        gt_pts = _gt_points(cloud, gt_boxes)
        for s in settings_list:
            fr = frame_features(cloud, None if s.proposal_mode == "exact" else det_msg,
                                None if s.proposal_mode == "none" else prop_msg, s,
                                intensity=scales[s.proposal_mode])
            builders[s.proposal_mode].add(fr, group, source.get("path", ""), key, gt_boxes,
                                          gt_labels, gt_ids, gt_pts)
        bar.update()
    bar.close()
    return {m: b.build({"sources": [dict(source)], "frames_without_gt": 0})
            for m, b in builders.items()}


def load_kitti(root, results, settings_list, *, split: str = "training", proposals=None,
               frames=None, group_digits: int = 2, cache_dir=None, class_aware: bool = False,
               progress: bool = True) -> dict[str, LmdDataset]:
    """``{mode: LmdDataset}`` of a KITTI object directory and detector result files.

    ``frames``: frame ids (or an ``ImageSets`` file); default every scan with a result
    file. ``proposals``: directory of per-frame proposal files, needed by the modes
    ``exact`` and ``threshold``.
    """
    root, results = Path(root), Path(results)
    settings_list = list(settings_list)
    modes = _modes_of(settings_list)
    if proposals is None and any(m != "none" for m in modes):
        raise ValueError(f"modes {[m for m in modes if m != 'none']} need proposal files "
                         f"(--kitti-proposals); without them only mode 'none' works")
    ids = _kitti_ids(root, split, results, frames)
    if not ids:
        raise FileNotFoundError(f"no frames: {results} has no result file for a scan in "
                                f"{root / split / 'velodyne'}")
    base = root / split
    files = [base / "velodyne" / f"{i}.bin" for i in ids]
    files += [base / "label_2" / f"{i}.txt" for i in ids]
    calibs = [base / "calib" / f"{i}.txt" for i in ids]
    missing = [c for c in calibs if not c.exists()]
    if missing:
        raise _no_calib(missing[0], len(missing) - 1)
    files += calibs
    files += [results / f"{i}.txt" for i in ids]
    if proposals is not None:
        files += [Path(proposals) / f"{i}.txt" for i in ids]
    for d in (results, proposals):  # the calibration a result file was written with
        if d is not None:
            files += [p for p in (Path(d) / "calib" / f"{i}.txt" for i in ids) if p.exists()]
    key = {"kind": "kitti", "files": _fingerprint(files), "group_digits": group_digits}
    got = _cached(cache_dir, f"kitti_{root.name}_{split}", settings_list, key,
                  lambda miss: _read_kitti(root, split, results, proposals, ids, miss,
                                           group_digits, progress), progress)
    return {m: ds.with_class_aware(class_aware) for m, ds in got.items()}


# ---------------------------------------------------------------------------- CLI glue
def add_source_args(ap, *, train: bool = True, test: bool = True) -> None:
    """Data arguments shared by ``lmd-train``, ``lmd-eval`` and the annotation review."""
    g = ap.add_argument_group("data (perception bags or a KITTI directory)")
    if train:
        g.add_argument("--train", nargs="+", type=Path, default=None,
                       help="training bags, or directories of bags "
                            "(default: data/perception/meta_train)")
    if test:
        g.add_argument("--test", nargs="*", type=Path, default=None,
                       help="held-out bags, or directories of bags (default: "
                            "data/perception/meta_test if it exists; give no value for none)")
    g.add_argument("--kitti-root", type=Path, default=None,
                   help="KITTI object directory (instead of bags)")
    g.add_argument("--kitti-split", default="training", help="sub-directory of --kitti-root")
    g.add_argument("--kitti-results", type=Path, default=None,
                   help="detector result files (KITTI result format, one per frame)")
    g.add_argument("--kitti-proposals", type=Path, default=None,
                   help="pre-NMS proposal files (same format), needed by modes exact/threshold")
    if train:
        g.add_argument("--kitti-train-frames", type=Path, default=None,
                       help="ImageSets-style file of the training frame ids")
    if test:
        g.add_argument("--kitti-test-frames", type=Path, default=None,
                       help="ImageSets-style file of the held-out frame ids")
    g.add_argument("--kitti-group-digits", type=int, default=2,
                   help="frame id prefix length that names the sequence (group)")
    add_topic_option(g)
    g.add_argument("--cache", type=lambda v: Path(v) if v else None,
                   default=Path("out/lmd/cache"),
                   help="feature cache directory ('' to disable)")
    g.add_argument("--class-aware", action="store_true",
                   help="target: IoU_BEV with the best GT box of the same class "
                        "(default: any class, as the authors)")
    s = ap.add_argument_group("feature settings (must match the node's parameters)")
    s.add_argument("--iou-threshold", type=float, default=0.5,
                   help="threshold mode: BEV IoU > t puts a proposal in the set")
    s.add_argument("--proposal-score-threshold", type=float, default=0.0,
                   help="threshold mode: proposals scoring <= this are ignored")
    s.add_argument("--intensity-scale", choices=INTENSITY_SCALES, default="auto",
                   help="the clouds' intensity scale, brought to [0, 1] (unit, byte = 0..255, "
                        "auto: decided per bag from its first frames, as the node does)")
    s.add_argument("--nms-iou-threshold", type=float, default=0.1, help="exact mode: NMS IoU")
    s.add_argument("--nms-score-threshold", type=float, default=0.1,
                   help="exact mode: proposals scoring below take no part in NMS")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")


def settings_from_args(args, modes) -> list:
    """One validated ``LmdSettings`` per mode from the feature-setting arguments."""
    return [settings_for(m, iou_threshold=args.iou_threshold,
                         proposal_score_threshold=args.proposal_score_threshold,
                         nms_iou_threshold=args.nms_iou_threshold,
                         nms_score_threshold=args.nms_score_threshold,
                         intensity_scale=getattr(args, "intensity_scale", "auto"))
            for m in modes]


def load_from_args(args, settings_list, part: str) -> dict[str, LmdDataset] | None:
    """``{mode: dataset}`` of the ``part`` (``"train"`` / ``"test"``) the arguments name,
    or None when there is no such part (no held-out data)."""
    cache = args.cache
    progress = not args.quiet
    if args.kitti_root is not None:
        if args.kitti_results is None:
            raise SystemExit("--kitti-root needs --kitti-results")
        frames = getattr(args, f"kitti_{part}_frames", None)
        if part == "test" and frames is None:
            return None
        return load_kitti(args.kitti_root, args.kitti_results, settings_list,
                          split=args.kitti_split, proposals=args.kitti_proposals, frames=frames,
                          group_digits=args.kitti_group_digits, cache_dir=cache,
                          class_aware=args.class_aware, progress=progress)
    paths = getattr(args, part, None)
    if paths is None:
        default = Path("data/perception") / f"meta_{part}"
        if part == "test" and not default.exists():
            return None
        paths = [default]
    if not paths:
        return None
    return load_bags(paths, settings_list, cache_dir=cache, class_aware=args.class_aware,
                     topics=dict(getattr(args, "topic", None) or ()), progress=progress)
