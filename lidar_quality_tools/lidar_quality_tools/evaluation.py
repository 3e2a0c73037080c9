"""Quality of the nodes' recorded outputs against the ground truth.

Input: the perception bag (clouds, detector outputs, ground truth) and a bag of the nodes'
outputs (recorded by the demo, or written by ``process_bag``: then both are one bag),
joined by header stamp. Per method the targets are those of its training data:

- LMD (``/lmd/output/quality``): each detection's BEV IoU with its best ground-truth box
  (any class), true positive at IoU >= 0.5 (``lidar_quality_training.lmd.dataset``); baseline: the detector
  score (``original_score``).
- LMS (``/lms/output/segments``): each segment's adjusted IoU, true segment at IoU_adj > 0
  (``lidar_quality_core.lms.segment_metrics.segment_targets``), computed on the segmentation recomputed
  from the input and checked against the recorded one (segment count, classes, sizes);
  baseline: the segment's mean top-class softmax probability (1 - mean V).
- MIMO (``/mimo/output/uncertainty``): each merged box's BEV IoU with its best
  ground-truth box of its class, true positive at >= 0.5 (``lidar_quality_training.mimo.dataset``); the
  merge is recomputed from the heads and checked against the recorded ids; baseline: the
  merged score.

A frame whose recorded output does not match its input (other ids, other segments) is
counted as ``mismatched`` and left out, so a wrong output cannot pass for a right one.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_quality_core import metrics
from lidar_quality_core.conventions import TP_IOU

#: method -> the output topic with its estimates (namespaced as the demo and
#: ``process_bag`` run the nodes)
OUTPUT_TOPICS = {"lmd": "/lmd/output/quality", "lms": "/lms/output/segments",
                 "mimo": "/mimo/output/uncertainty"}
METHODS = tuple(OUTPUT_TOPICS)
BASELINES = {"lmd": "detector score", "lms": "mean softmax probability",
             "mimo": "merged score"}
#: per-row columns of every method
COLUMNS = ("tp", "iou", "confidence", "predicted_iou", "baseline")


class Mismatch(ValueError):
    """A recorded output that does not belong to its input frame."""


@dataclass
class MethodRows:
    """Evaluated rows of one method (one per detection / segment with a confidence)."""

    method: str
    frames_in: int = 0        # input frames with this method's inputs
    frames_out: int = 0       # of which with a recorded output
    mismatched: int = 0       # recorded outputs that do not match their input (left out)
    mismatch_reasons: list = field(default_factory=list)
    parts: dict = field(default_factory=lambda: {k: [] for k in COLUMNS})

    def add(self, **cols) -> None:
        n = len(cols["confidence"])
        for k, v in cols.items():
            self.parts[k].append(np.asarray(v, np.float64).reshape(n))

    def column(self, key: str) -> np.ndarray:
        p = self.parts[key]
        return np.concatenate(p) if p else np.zeros(0)

    def quality(self, n_bins: int = 10) -> dict:
        """AUROC / ECE of the confidence and of the baseline, R² of the predicted IoU."""
        conf, base = self.column("confidence"), self.column("baseline")
        tp, iou, piou = self.column("tp"), self.column("iou"), self.column("predicted_iou")
        ok = np.isfinite(conf) & np.isfinite(iou) & np.isfinite(base)
        out = {"n": int(ok.sum()), "positive_rate": float(tp[ok].mean()) if ok.any() else None,
               "baseline": BASELINES[self.method]}
        both = ok.any() and 0 < tp[ok].sum() < ok.sum()  # AUROC needs both outcomes
        out["auroc"] = metrics.auroc(tp[ok], conf[ok]) if both else None
        out["auroc_baseline"] = metrics.auroc(tp[ok], base[ok]) if both else None
        out["ece"] = metrics.ece(tp[ok], np.clip(conf[ok], 0, 1), n_bins) if ok.any() else None
        out["ece_baseline"] = (metrics.ece(tp[ok], np.clip(base[ok], 0, 1), n_bins)
                               if ok.any() else None)
        okr = ok & np.isfinite(piou)
        out["r2"] = metrics.r2(iou[okr], piou[okr]) if okr.sum() > 1 else None
        return out


# ------------------------------------------------------------------ per frame
def _gt(gt_msg):
    from lidar_quality_core.boxes import detections_to_arrays

    g = detections_to_arrays(gt_msg)
    return g.boxes[g.valid], [c for c, ok in zip(g.labels, g.valid) if ok]


def lmd_rows(detections_msg, gt_msg, quality_msg, *, index_ids: bool = False) -> dict:
    """Rows of one frame: the recorded quality of each input detection and its target.
    ``index_ids``: the node read the detections as Autoware objects (no ids: each one's
    id is its index)."""
    from lidar_quality_core.boxes import detections_to_arrays
    from lidar_quality_core.detection_eval import match_frame

    d = detections_to_arrays(detections_msg)
    q = quality_msg.detections
    ids = [str(i) for i in range(len(d.ids))] if index_ids else list(d.ids)
    if [x.detection_id for x in q] != ids or \
            [x.detection_index for x in q] != list(range(len(d.ids))):
        raise Mismatch(f"LMD quality lists {len(q)} detections, the input {len(d.ids)} "
                       "(or other ids / order)")
    conf = np.array([x.confidence for x in q], float)
    ok = d.valid & np.isfinite(conf)
    gt_boxes, gt_labels = _gt(gt_msg)
    labels = [c for c, k in zip(d.labels, ok) if k]
    m = match_frame(d.boxes[ok], d.scores[ok], labels, gt_boxes, gt_labels, iou_threshold=TP_IOU)
    idx = np.flatnonzero(ok)
    return {"confidence": conf[idx], "predicted_iou": [q[i].predicted_iou for i in idx],
            "baseline": [q[i].original_score for i in idx], "iou": m.iou_any,
            "tp": m.iou_any >= TP_IOU, "boxes": d.boxes[idx], "gt_boxes": gt_boxes}


def lms_rows(points_msg, segmentation_msg, points_gt_msg, segments_msg, settings,
             *, separate: bool = True) -> dict:
    """Rows of one frame: recorded quality of each segment with a defined IoU_adj.

    ``separate``: the node read the points and the probabilities on two topics (the ring
    field of the points then gives the image rows, as the shipped models were trained).
    """
    from lidar_quality_training.lms.dataset import _gt_labels, frame_rows
    from lms_ros.pipeline import decode

    inp = (decode(points_msg, settings, probabilities_msg=segmentation_msg) if separate
           else decode(segmentation_msg, settings))
    res, iou, iou_adj, keep = frame_rows(inp, _gt_labels(points_gt_msg), settings)
    s = segments_msg.segments
    rec = np.array([(x.segment_id, x.class_index, x.point_count) for x in s],
                   np.int64).reshape(-1, 3)
    if len(s) != res.n_segments or not (
            np.array_equal(rec[:, 0], np.arange(res.n_segments))
            and np.array_equal(rec[:, 1], res.segment_class)
            and np.array_equal(rec[:, 2], res.n_points)):
        raise Mismatch(f"LMS recorded {len(s)} segments, the input gives {res.n_segments} "
                       "(or other classes / sizes)")
    sid = res.kept_ids[keep]
    conf = np.array([s[i].confidence for i in sid.tolist()], float)
    v = settings.metric_names().index("mean_V")
    return {"confidence": conf, "predicted_iou": [s[i].predicted_iou for i in sid.tolist()],
            "baseline": 1.0 - res.features[keep, v], "iou": iou_adj[keep],
            "tp": iou_adj[keep] > 0, "segment_ids": sid, "result": res, "input": inp}


def mimo_rows(head_msgs, variance_msgs, gt_msg, uncertainty_msg, settings, *,
              index_ids: bool = False) -> dict:
    """Rows of one frame: the merge recomputed from the heads, checked against the
    recorded ids, with the recorded confidence and predicted IoU. ``index_ids``: the node
    read the heads as Autoware objects (a member's id is its index in its head)."""
    from lidar_quality_core.detection_eval import match_frame
    from mimo_ros.pipeline import frame_features

    frame = frame_features(head_msgs, variance_msgs, settings)
    ids = frame.merged_ids(by_index=index_ids)
    c = uncertainty_msg.clusters
    if [x.detection_id for x in c] != list(ids):
        raise Mismatch(f"MIMO recorded {len(c)} merged boxes, the heads give {len(ids)} "
                       "(or other ids)")
    m = frame.merge
    gt_boxes, gt_labels = _gt(gt_msg)
    labels = frame.class_labels()
    mt = match_frame(m.boxes, m.scores, labels, gt_boxes, gt_labels, iou_threshold=TP_IOU)
    return {"confidence": [x.confidence for x in c], "predicted_iou": [x.predicted_iou for x in c],
            "baseline": m.scores, "iou": mt.iou_same_class, "tp": mt.iou_same_class >= TP_IOU,
            "boxes": m.boxes, "gt_boxes": gt_boxes}


# ------------------------------------------------------------------ bags
def read_outputs(bag: Path | str, methods=METHODS) -> dict[str, dict[int, object]]:
    """The recorded estimates of ``methods``: their ``OUTPUT_TOPICS`` messages by topic
    and header stamp [ns]."""
    from lidar_quality_core.time_sync import stamp_to_ns
    from lidar_quality_ros.bag_io import bag_topics, read_bag

    present = bag_topics(bag)
    topics = {OUTPUT_TOPICS[m] for m in methods if OUTPUT_TOPICS[m] in present}
    out: dict[str, dict[int, object]] = {t: {} for t in topics}
    for m in read_bag(bag, topics=topics):
        msg = m.decode()
        out[m.topic][stamp_to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg
    return out


@dataclass
class Evaluation:
    rows: dict                                   # method -> MethodRows
    frames: int                                  # input frames read
    example: dict = field(default_factory=dict)  # method -> rows of one frame (plots)
    example_frame: int | None = None             # its index; None: no frame every method answered
    example_target: int = 0                      # the frame asked for (default: the middle one)
    answered_by_all: int = 0                     # frames with matching rows of every method

    def quality(self) -> dict:
        return {m: {"frames_in": r.frames_in, "frames_out": r.frames_out,
                    "mismatched": r.mismatched, **r.quality()} for m, r in self.rows.items()}


def evaluate(perception_bag, outputs_bag=None, *, methods=METHODS, lms_settings=None,
             mimo_settings=None, lms_separate: bool = True, example_frame: int | None = None,
             progress: bool = False, autoware: bool = False) -> Evaluation:
    """Join the recorded outputs with the inputs and ground truth of ``perception_bag``
    (``outputs_bag`` None: the outputs are in it too) and collect every method's rows.

    The rows of one frame are kept for plots (``ev.example``): the frame nearest to
    ``example_frame`` (default: the middle one; ties: the earlier) that every method of
    ``methods`` answered with a matching output, so that the pictures show all of them
    on one frame. No such frame: ``ev.example`` is empty and ``ev.example_frame`` None.
    ``autoware``: LMD and MIMO read the detections as Autoware objects (ids = indices)."""
    from lidar_quality_core.progress import Progress
    from lidar_quality_ros.bag_io import bag_info
    from lidar_quality_ros.perception_bag import perception_frames
    from lms_ros.pipeline import LmsSettings
    from mimo_ros.pipeline import MimoSettings

    lms_settings = lms_settings or LmsSettings()
    mimo_settings = mimo_settings or MimoSettings()
    outs = read_outputs(outputs_bag or perception_bag, methods)
    info = bag_info(perception_bag)
    n_total = info.topics["/lidar/points"].count if "/lidar/points" in info.topics else None
    if example_frame is None:
        example_frame = (n_total or 0) // 2
    rows = {m: MethodRows(m) for m in methods}
    ev = Evaluation(rows, 0, example_target=example_frame)
    bar = Progress("evaluate", n_total, progress)
    want = ("points", "points_gt", "gt_objects", "detections", "segmentation")
    heads = mimo_settings.num_heads if "mimo" in methods else 0
    for f in perception_frames(perception_bag, want=want, heads=heads):
        bar.update()
        ev.frames += 1
        if f.gt_objects is None or f.points_gt is None:
            continue  # no targets without ground truth
        answered = {}    # method -> this frame's rows
        for m in methods:
            r = rows[m]
            if m == "lmd" and f.detections is not None:
                args = (f.detections, f.gt_objects)
            elif m == "lms" and f.segmentation is not None:
                args = (f.points, f.segmentation, f.points_gt)
            elif m == "mimo" and all(h is not None for h in f.heads):
                args = (f.heads, f.head_variances, f.gt_objects)
            else:
                continue
            r.frames_in += 1
            rec = outs.get(OUTPUT_TOPICS[m], {}).get(f.stamp_ns)
            if rec is None:
                continue
            r.frames_out += 1
            try:
                if m == "lmd":
                    got = lmd_rows(*args, rec, index_ids=autoware)
                elif m == "lms":
                    got = lms_rows(*args, rec, lms_settings, separate=lms_separate)
                else:
                    got = mimo_rows(*args, rec, mimo_settings, index_ids=autoware)
            except Mismatch as e:
                r.mismatched += 1
                if len(r.mismatch_reasons) < 5:
                    r.mismatch_reasons.append(f"stamp {f.stamp_ns}: {e}")
                continue
            r.add(**{k: got[k] for k in COLUMNS})
            answered[m] = got
        if len(answered) == len(methods):
            ev.answered_by_all += 1
            if ev.example_frame is None or (abs(f.index - example_frame)
                                            < abs(ev.example_frame - example_frame)):
                ev.example_frame = f.index
                ev.example = {m: {**got, "stamp_ns": f.stamp_ns, "frame": f.index,
                                  "points": f.points} for m, got in answered.items()}
    bar.close()
    return ev


def main(argv=None) -> int:
    """``python -m lidar_quality_tools.evaluation --bag PERCEPTION_BAG [--outputs BAG]``:
    the quality of recorded (or ``process_bag``-annotated) outputs, as JSON on stdout."""
    from .process import node_parameters, node_settings

    ap = argparse.ArgumentParser(description=main.__doc__.split("\n")[0])
    ap.add_argument("--bag", type=Path, required=True, help="perception bag with ground truth")
    ap.add_argument("--outputs", type=Path, default=None,
                    help="bag of the nodes' outputs (default: in --bag, as process_bag writes)")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="the node parameters the outputs were made with (lms, mimo)")
    a = ap.parse_args(argv)
    import yaml
    over: dict = {"lms": {}, "mimo": {}}
    for item in a.param:
        key, _, value = item.partition("=")
        node, _, name = key.partition(".")
        if node not in over or not name or not _:
            ap.error(f"--param {item!r}: expected lms.NAME=VALUE or mimo.NAME=VALUE")
        over[node][name] = yaml.safe_load(value)
    lms_p = node_parameters("lms", over["lms"])
    ev = evaluate(a.bag, a.outputs, lms_settings=node_settings("lms", lms_p),
                  mimo_settings=node_settings("mimo", node_parameters("mimo", over["mimo"])),
                  lms_separate=bool(lms_p["separate_probabilities"]), progress=True)
    from lidar_quality_core.jsonable import jsonable
    json.dump(jsonable(ev.quality()), sys.stdout, indent=1)
    print()
    return 1 if any(r.mismatched for r in ev.rows.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
