"""Per-detection and per-segment results of the nodes as Parquet tables (pyarrow).

One row per scored item of a processed frame, in output order:

* ``lmd``: every detection the node scored (``valid`` false: no features, NaN values);
* ``mimo``: every merged detection;
* ``lms``: every kept segment (the ones with metrics and a confidence).

The format is ``lidar_quality_training.feature_table``'s (its column names, metadata and
atomic writer), so that the table of a labelled bag trains a meta model
(``lmd-train --features``); these tables add the nodes' outputs. Columns: ``group``
(``bag_group``), ``source`` (the bag), ``frame_key`` (header stamp [ns] as text), ``stamp_ns``, ``frame_id``,
``index`` (position among the frame's items: detection index, merged index or segment
id), the outputs ``confidence``, ``predicted_iou`` and (detections) ``kept``, the frame's
drift verdict as its quality message carries it (``drift_level``: off, warming up, OK,
WARN, ERROR; ``drift_score``, NaN before a score; ``passthrough``: the confidences are the
detector's scores, or NaN for LMS, not the meta models'), the
features as ``feat.<name>`` in the model's order, and per method:

* ``lmd`` / ``mimo``: ``det_id``, ``label``, ``score``, ``box_x`` .. ``box_yaw``, ``valid``
  (lmd); targets ``iou_any`` / ``iou_class`` (IoU_BEV with the best ground-truth box of
  any / the same class, ``detection_eval.match_frame``) when the bag has ground-truth
  objects (``gt_objects`` topic), else NaN;
* ``lms``: ``segment_class`` (class index), ``label`` (its name), ``size``,
  ``size_projected``, ``n_points``; targets ``iou`` / ``iou_adj``
  (``lms.targets.segment_targets``, label 0 ignored) when the bag has the ground-truth
  cloud (``points_gt`` topic, one label per input point), else NaN.

Schema metadata: ``feature_table.schema_metadata`` (method, mode, feature names,
settings) plus ``lq.models`` (JSON: the ids of the models that gave the outputs).
"""
from __future__ import annotations

import dataclasses
import json
from collections import Counter

import numpy as np
from lidar_quality_training.feature_table import FEATURE_PREFIX, schema_metadata, write_table

__all__ = ["FEATURE_PREFIX", "BOX_COLUMNS", "ResultRows", "write_table"]

BOX_COLUMNS = ("box_x", "box_y", "box_z", "box_l", "box_w", "box_h", "box_yaw")
IGNORE_LABEL = 0   # the LMS datasets' unlabelled class


def _text(values, n) -> np.ndarray:
    return np.array([str(v) for v in values], dtype=object).reshape(n)


class ResultRows:
    """Collects the rows of one bag (or slice): ``collect(node, frame, outputs)`` is the
    hook of ``process._run``; ``tables()`` gives one pyarrow Table per node with rows.
    Ground truth that is there but cannot be used (undecodable, another cloud) leaves the
    frame's targets NaN: counted by cause in ``issues``, and ``warn(text)`` called the
    first time of each cause."""

    def __init__(self, runners, *, source: str, group: str, gt_topics: dict | None = None,
                 warn=None):
        self.source, self.group = str(source), group
        self.gt = dict(gt_topics or {})          # "gt_objects" / "points_gt" -> topic
        self.parts: dict[str, list[dict]] = {r.name: [] for r in runners}
        self.meta = {r.name: _meta(r) for r in runners}
        self.issues: Counter = Counter()
        self.warn = warn

    def _unusable(self, cause: str, text: str) -> None:
        self.issues[cause] += 1
        if self.issues[cause] == 1 and self.warn is not None:
            self.warn(f"{text}: targets NaN (counted as results_issues.{cause})")

    def collect(self, node: str, frame, out) -> None:
        rows = {"lmd": self._lmd, "mimo": self._mimo, "lms": self._lms}[node](frame, out)
        n = len(rows["index"])
        rows = {"group": _text([self.group] * n, n), "source": _text([self.source] * n, n),
                "frame_key": _text([frame.stamp_ns] * n, n),
                "stamp_ns": np.full(n, frame.stamp_ns, np.int64), **rows}
        self.parts[node].append(rows)

    def _gt(self, frame, key):
        topic = self.gt.get(key)
        if topic is None or topic not in frame.msgs:
            return None
        try:
            return frame.get(topic)
        except Exception as exc:  # noqa: BLE001 - undecodable ground truth: no targets
            self._unusable(f"undecodable_{key}", f"{topic} not decoded ({exc})")
            return None

    def _box_targets(self, frame, boxes, scores, labels, ok):
        """``(iou_any, iou_class)`` of the rows ``ok`` against the frame's ground truth."""
        from lidar_quality_core.boxes import detections_to_arrays
        from lidar_quality_core.conventions import TP_IOU
        from lidar_quality_core.detection_eval import match_frame

        n = len(scores)
        iou_any, iou_class = np.full(n, np.nan), np.full(n, np.nan)
        msg = self._gt(frame, "gt_objects")
        if msg is None:
            return iou_any, iou_class
        gt = msg.arrays if hasattr(msg, "arrays") else detections_to_arrays(msg)
        idx = np.flatnonzero(ok)
        m = match_frame(boxes[idx], scores[idx], [labels[i] for i in idx.tolist()],
                        gt.boxes[gt.valid], [c for c, v in zip(gt.labels, gt.valid) if v],
                        iou_threshold=TP_IOU)
        iou_any[idx], iou_class[idx] = m.iou_any, m.iou_same_class
        return iou_any, iou_class

    def _lmd(self, frame, out) -> dict:
        f = out.frame
        d, n = f.detections, len(f.detections)
        boxes = np.asarray(d.boxes, np.float64).reshape(n, 7)
        iou_any, iou_class = self._box_targets(frame, boxes, d.scores, d.labels, f.valid)
        return {"frame_id": _text([_frame_id(f.header)] * n, n),
                "index": np.arange(n, dtype=np.int32), "det_id": _text(d.ids, n),
                "label": _text(d.labels, n), "score": np.asarray(d.scores, np.float64),
                **{c: boxes[:, j] for j, c in enumerate(BOX_COLUMNS)},
                "valid": np.asarray(f.valid, bool),
                "confidence": np.asarray(out.confidence, np.float64),
                "predicted_iou": np.asarray(out.predicted_iou, np.float64),
                "kept": np.asarray(out.kept, bool), **_drift(out.quality, n),
                "iou_any": iou_any, "iou_class": iou_class,
                **_features(self.meta["lmd"]["feature_names"], f.features, n)}

    def _mimo(self, frame, out) -> dict:
        o = out.out
        fr, m = o.frame, o.frame.merge
        n = len(m.scores)
        labels = [fr.class_names[int(c) - 1] for c in m.labels]
        boxes = np.asarray(m.boxes, np.float64).reshape(n, 7)
        iou_any, iou_class = self._box_targets(frame, boxes, m.scores, labels, np.ones(n, bool))
        kept = np.ones(n, bool) if o.kept is None else np.asarray(o.kept, bool)
        return {"frame_id": _text([_frame_id(getattr(o.uncertainty, "header", None))] * n, n),
                "index": np.arange(n, dtype=np.int32), "det_id": _text(fr.merged_ids(), n),
                "label": _text(labels, n), "score": np.asarray(m.scores, np.float64),
                **{c: boxes[:, j] for j, c in enumerate(BOX_COLUMNS)},
                "confidence": np.asarray(o.confidence, np.float64),
                "predicted_iou": np.asarray(o.predicted_iou, np.float64), "kept": kept,
                **_drift(o.uncertainty, n), "iou_any": iou_any, "iou_class": iou_class,
                **_features(self.meta["mimo"]["feature_names"], fr.features, n)}

    def _lms(self, frame, out) -> dict:
        res = out.result
        ids = np.asarray(res.kept_ids, np.int64)
        n = len(ids)
        iou, iou_adj = np.full(n, np.nan), np.full(n, np.nan)
        gt_msg = self._gt(frame, "points_gt")
        if gt_msg is not None:
            from lidar_quality_core.lms.targets import segment_targets
            from lidar_quality_core.pointcloud import read_fields

            try:
                gt = read_fields(gt_msg, ["label"], dtype=np.int64)[:, 0]
                iou, iou_adj = segment_targets(res, gt, ignore_label=IGNORE_LABEL)
            except (ValueError, KeyError) as exc:   # another cloud, or no label field
                self._unusable("points_gt_mismatch", f"{self.gt['points_gt']} does not "
                               f"label the segmented cloud ({exc})")
        cls = np.asarray(res.segment_class)[ids].astype(np.int64)
        names = res.class_names or ()
        label = [names[c] if 0 <= c < len(names) else str(c) for c in cls.tolist()]
        return {"frame_id": _text([_frame_id(getattr(out.segments, "header", None))] * n, n),
                "index": ids.astype(np.int32), "segment_class": cls, "label": _text(label, n),
                "size": np.asarray(res.size)[ids].astype(np.int64),
                "size_projected": np.asarray(res.size_projected)[ids].astype(np.int64),
                "n_points": np.asarray(res.n_points)[ids].astype(np.int64),
                "confidence": np.asarray(out.confidence, np.float64)[ids],
                "predicted_iou": np.asarray(out.predicted_iou, np.float64)[ids],
                **_drift(out.segments, n),
                "iou": np.asarray(iou, np.float64), "iou_adj": np.asarray(iou_adj, np.float64),
                **_features(res.names, res.features, n)}

    def tables(self) -> dict:
        """node -> pyarrow Table of its rows (nodes without a row are left out)."""
        import pyarrow as pa

        out = {}
        for node, parts in self.parts.items():
            if not parts:
                continue
            cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
            table = pa.table({k: pa.array(v) for k, v in cols.items()})
            m = self.meta[node]
            meta = schema_metadata(node, m["mode"], m["feature_names"], m["settings"])
            out[node] = table.replace_schema_metadata(
                {**meta, b"lq.models": json.dumps(m["models"]).encode()})
        return out


def _frame_id(header) -> str:
    return getattr(header, "frame_id", "") or ""


def _drift(msg, n) -> dict:
    """The drift columns of a frame's ``n`` rows from its quality array message."""
    from lidar_quality_core.domain_profile import STATE_CONSTANTS

    names = {getattr(type(msg), c): s for s, c in STATE_CONSTANTS.items()}
    return {"drift_level": _text([names.get(msg.drift_level, "unknown")] * n, n),
            "drift_score": np.full(n, msg.drift_score, np.float64),
            "passthrough": np.full(n, bool(msg.passthrough))}


def _features(names, X, n) -> dict:
    X = np.asarray(X, np.float64).reshape(n, len(names))
    return {FEATURE_PREFIX + name: np.ascontiguousarray(X[:, j]) for j, name in enumerate(names)}


def _settings_json(settings) -> dict:
    d = dataclasses.asdict(settings) if dataclasses.is_dataclass(settings) else {}
    return json.loads(json.dumps(d, default=str))


def _meta(runner) -> dict:
    """The table metadata of a runner's node: method, mode, features, settings, models."""
    s = runner.processor.settings
    ids = runner.model_ids()
    if runner.name == "lmd":
        mode, names = s.proposal_mode, list(s.feature_names())
    elif runner.name == "mimo":
        mode, names = "points" if s.use_points else "no_points", list(s.feature_names())
    else:   # the mode: where the image rows come from
        mode = "points" if "points" in runner.topics else "segmentation"
        names = list(s.metric_names())
    return {"method": runner.name, "mode": mode, "feature_names": names,
            "settings": _settings_json(s), "models": ids}
