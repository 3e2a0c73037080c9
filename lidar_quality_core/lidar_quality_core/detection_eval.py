"""Matching of 3D / BEV detections to ground truth, KITTI-style AP, LiDAR-MIMO partitions.

The single place where detections become TP / FP: the reference detector's quality
report, the LMD meta classification targets and the LiDAR-MIMO evaluation all use it.

Matching (``match_frame``), per frame, class-aware, COCO / KITTI-style greedy:

* Detections are visited by descending score; equal scores keep input order (stable).
* A detection may match a GT box of its own class with ``IoU >= t`` (``IoU > t`` with
  ``strict=True``, as in the KITTI devkit and the LiDAR-MIMO authors' code), ``t`` the
  IoU threshold of the detection's class. Among those it takes the free, non-ignored
  GT box of highest IoU (ties: lowest GT index), so a lower-scored detection can still
  match a second GT box after a higher one took its best (COCO; VOC would call it an FP).
  Each such GT box is matched at most once: a later detection of the same object with no
  other free GT box is an FP (a duplicate).
* Otherwise, if an ignored GT box (``gt_ignore``) qualifies, the detection is "ignored":
  neither TP nor FP, and left out of AP. Ignored GT boxes absorb any number of detections
  (like KITTI DontCare regions and COCO crowd boxes) and never count as ground truth.
* ``iou_same_class`` / ``iou_any`` are plain maxima over *all* GT boxes, ignored ones
  included, with no one-to-one constraint. ``FrameMatch.hit()`` gives the LMD target
  (IoU with the best-matching GT box >= 0.5, duplicates included; class-agnostic in the
  LMD authors' code, class-aware as an option).

Average precision (``average_precision``), the exact definition:

* All non-ignored detections (of one class, over all frames) are sorted by descending
  score. Operating points are the distinct scores ``s``: every detection with score >= s
  is accepted, so tied detections enter together and their order does not matter.
  At each point ``recall = TP / n_gt`` and ``precision = TP / (TP + FP)``.
* Interpolated precision ``p(r) = max{precision_j : recall_j >= r}``, 0 if no point
  reaches ``r``.
* R40 (KITTI since 2019, the LiDAR-MIMO mAP): mean of ``p(r)`` over ``r = 1/40, ..., 40/40``.
  R11 (KITTI before 2019, VOC 2007): mean over ``r = 0, 0.1, ..., 1``. R101 (COCO): over
  ``r = 0, 0.01, ..., 1``. ``recall >= k / K`` is tested in integers (``TP * K >= k * n_gt``),
  so no level is lost to rounding. AP with ``n_gt == 0`` is undefined: ``nan``.
* The KITTI devkit samples the same curve at thresholds taken from the TP scores, which
  approximates this; the exact form here is what the tests check.

Detection partitions (``fp_partition``), LiDAR-MIMO (Pitropov et al.), section IV.C,
"Detection partitions", quoted:

    "True Positives (TP) are predictions that match a ground-truth (GT) box with an IoU
    over the TP IoU threshold. Mis-localized false positives (FP_ML) are predictions that
    match with a GT box, but their IoU is below the TP IoU threshold and higher than 0.1.
    The last partition is background false positives (FP_BG), where the prediction has a
    lower than 0.1 IoU with all GT boxes and thus it is highly likely that the prediction
    should be background."

The paper leaves open IoU == 0.1, duplicates and class errors. Here: TP = ``FrameMatch.tp``;
FP_BG iff ``iou_any <= 0.1`` against every GT box of any class (the authors' code,
mpitropov/detection_eval: background iff not IoU > 0.1); every other non-ignored
detection is FP_ML, i.e. it overlaps some GT box by more than 0.1 but fails the IoU
criterion, the class criterion or the one-to-one match (duplicate). With
``separate_duplicates=True`` duplicates (own-class IoU passing the threshold, GT box already
taken) get their own label, as in the authors' final evaluation script. That script's
reported FP_ML column holds only the correctly classified ones (best-overlap GT box of the
detection's class): ``(codes == FP_ML) & (m.labels == m.gt_labels[m.gt_any])``.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from .box_geometry import as_boxes
from .iou import iou_3d, iou_bev

__all__ = ["FrameMatch", "match_frame", "precision_recall", "average_precision",
           "summarize", "evaluate", "Partition", "fp_partition", "partition_counts",
           "KITTI_IOU_THRESHOLDS", "MIMO_BG_IOU"]

KITTI_IOU_THRESHOLDS = {"car": 0.7, "pedestrian": 0.5, "cyclist": 0.5}
MIMO_BG_IOU = 0.1  # LiDAR-MIMO: below this IoU with every GT box a prediction is background


@dataclass(frozen=True)
class FrameMatch:
    """Result of ``match_frame`` for one frame; N detections, M GT boxes.

    ``det_gt`` / ``gt_det`` pair indices (-1: none). A detection with ``ignored`` True has
    ``det_gt`` pointing at the ignored GT box it hit; ``gt_det`` of ignored GT boxes is -1.
    """

    scores: np.ndarray          # (N,) float64
    labels: np.ndarray          # (N,) object, detection classes
    gt_labels: np.ndarray       # (M,) object
    gt_ignore: np.ndarray       # (M,) bool
    threshold: np.ndarray       # (N,) IoU threshold of each detection's class
    det_gt: np.ndarray          # (N,) int64
    tp: np.ndarray              # (N,) bool
    ignored: np.ndarray         # (N,) bool: matched an ignored GT box only
    iou_matched: np.ndarray     # (N,) IoU with det_gt, nan when unmatched
    iou_same_class: np.ndarray  # (N,) max IoU to any GT box of the same class
    iou_any: np.ndarray         # (N,) max IoU to any GT box, any class
    gt_any: np.ndarray          # (N,) int64 argmax of iou_any, -1 when iou_any == 0
    gt_det: np.ndarray          # (M,) int64
    strict: bool = False

    @property
    def fp(self) -> np.ndarray:
        """(N,) bool: neither TP nor ignored."""
        return ~self.tp & ~self.ignored

    @property
    def n_gt(self) -> int:
        """Number of non-ignored GT boxes."""
        return int(np.count_nonzero(~self.gt_ignore))

    def hit(self, class_aware: bool = True) -> np.ndarray:
        """(N,) bool: IoU with the best GT box passes the threshold, no one-to-one match.

        The LMD meta classification target (duplicates of a well-found object count).
        """
        iou = self.iou_same_class if class_aware else self.iou_any
        return iou > self.threshold if self.strict else iou >= self.threshold


def _labels(labels: Any, n: int, name: str) -> np.ndarray:
    if labels is None:
        raise ValueError(f"{name} is required")
    out = np.empty(n, dtype=object)
    seq = list(labels.tolist() if isinstance(labels, np.ndarray) else labels)
    if len(seq) != n:
        raise ValueError(f"{name} has {len(seq)} entries for {n} boxes")
    out[:] = seq
    return out


def _check_threshold(t: Any, what: str) -> float:
    t = float(t)
    if not 0.0 < t <= 1.0:  # t = 0 would match boxes that do not touch
        raise ValueError(f"IoU threshold {what} must lie in (0, 1], got {t}")
    return t


def _det_thresholds(iou_threshold: Any, labels: np.ndarray) -> np.ndarray:
    if isinstance(iou_threshold, Mapping):
        table = {k: _check_threshold(v, f"of class {k!r}") for k, v in iou_threshold.items()}
        missing = sorted({repr(c) for c in labels if c not in table})
        if missing:
            raise ValueError(f"no IoU threshold for detection class(es) {', '.join(missing)}")
        return np.array([table[c] for c in labels], dtype=np.float64)
    return np.full(len(labels), _check_threshold(iou_threshold, "iou_threshold"))


def _scores(scores: Any, n: int, name: str = "det_scores") -> np.ndarray:
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(s) != n:
        raise ValueError(f"{name} has {len(s)} entries for {n} detections")
    if np.isnan(s).any():
        raise ValueError(f"{name} contains NaN at index {int(np.flatnonzero(np.isnan(s))[0])}")
    return s


def match_frame(det_boxes, det_scores, det_labels, gt_boxes, gt_labels, *,
                iou_threshold: float | Mapping[Any, float], mode: str = "bev",
                gt_ignore=None, strict: bool = False) -> FrameMatch:
    """Greedy, class-aware, score-ordered matching of one frame (see module docstring).

    Boxes are (N, 7) / (M, 7) ``x, y, z, l, w, h, yaw`` (centre); ``iou_threshold`` is one
    value or a dict class -> threshold covering every detection class; ``mode`` is
    ``"bev"`` or ``"3d"``. NaN scores raise ValueError.
    """
    if mode not in ("bev", "3d"):
        raise ValueError(f"mode must be 'bev' or '3d', got {mode!r}")
    db, gb = as_boxes(det_boxes), as_boxes(gt_boxes)
    n, m = len(db), len(gb)
    scores = _scores(det_scores, n)
    dl = _labels(det_labels, n, "det_labels")
    gl = _labels(gt_labels, m, "gt_labels")
    if gt_ignore is None:
        ign = np.zeros(m, dtype=bool)
    else:
        ign = np.asarray(gt_ignore, dtype=bool).reshape(-1)
        if len(ign) != m:
            raise ValueError(f"gt_ignore has {len(ign)} entries for {m} GT boxes")
    thr = _det_thresholds(iou_threshold, dl)

    iou = (iou_bev if mode == "bev" else iou_3d)(db, gb)
    # integer class codes: equality by Python value, whatever the label types
    vocab: dict[Any, int] = {}
    dc = np.array([vocab.setdefault(c, len(vocab)) for c in dl], dtype=np.int64)
    gc = np.array([vocab.setdefault(c, len(vocab)) for c in gl], dtype=np.int64)
    same = dc[:, None] == gc[None, :]
    iou_same = np.where(same, iou, 0.0).max(axis=1, initial=0.0)
    iou_any = iou.max(axis=1, initial=0.0)
    gt_any = np.where(iou_any > 0, iou.argmax(axis=1) if m else -1, -1).astype(np.int64)
    ok = same & ((iou > thr[:, None]) if strict else (iou >= thr[:, None]))

    det_gt = np.full(n, -1, dtype=np.int64)
    gt_det = np.full(m, -1, dtype=np.int64)
    tp = np.zeros(n, dtype=bool)
    ignored = np.zeros(n, dtype=bool)
    taken = ign.copy()  # ignored GT boxes are never "taken" by a TP
    order = np.argsort(-scores, kind="stable")
    # Only detections with a qualifying GT box need the sequential pass.
    for i in order[ok[order].any(axis=1)]:
        row = ok[i]
        free = row & ~taken
        if free.any():
            j = int(np.argmax(np.where(free, iou[i], -1.0)))
            taken[j] = True
            gt_det[j] = i
            tp[i] = True
        else:
            hits_ignored = row & ign
            if not hits_ignored.any():
                continue  # duplicate: its GT boxes are taken
            j = int(np.argmax(np.where(hits_ignored, iou[i], -1.0)))
            ignored[i] = True
        det_gt[i] = j
    iou_matched = np.full(n, np.nan)
    has = det_gt >= 0
    iou_matched[has] = iou[np.flatnonzero(has), det_gt[has]]
    return FrameMatch(scores=scores, labels=dl, gt_labels=gl, gt_ignore=ign, threshold=thr,
                      det_gt=det_gt, tp=tp, ignored=ignored, iou_matched=iou_matched,
                      iou_same_class=iou_same, iou_any=iou_any, gt_any=gt_any, gt_det=gt_det,
                      strict=bool(strict))


# ------------------------------------------------------------------------------ AP
def _tp_array(tp: Any, n: int) -> np.ndarray:
    t = np.asarray(tp).reshape(-1)
    if len(t) != n:
        raise ValueError(f"tp has {len(t)} entries for {n} scores")
    if t.dtype != bool:
        if not np.isin(t, (0, 1)).all():
            raise ValueError("tp must be boolean (or 0/1)")
        t = t.astype(bool)
    return t


def _curve(scores: np.ndarray, tp: np.ndarray):
    """Cumulative TP and detection counts at each distinct score, descending."""
    order = np.argsort(-scores, kind="stable")
    s, t = scores[order], tp[order]
    ends = np.flatnonzero(np.r_[s[1:] != s[:-1], True]) if len(s) else np.zeros(0, np.intp)
    return np.cumsum(t)[ends], ends + 1, s[ends]


def _gather(matches, label) -> tuple[np.ndarray, np.ndarray, int]:
    if isinstance(matches, FrameMatch):
        matches = [matches]
    scores, tps, n_gt = [], [], 0
    for fm in matches:
        if not isinstance(fm, FrameMatch):
            raise TypeError(f"expected FrameMatch objects, got {type(fm).__name__}")
        keep = ~fm.ignored
        gt = ~fm.gt_ignore
        if label is not None:
            keep &= fm.labels == label
            gt &= fm.gt_labels == label
        scores.append(fm.scores[keep])
        tps.append(fm.tp[keep])
        n_gt += int(np.count_nonzero(gt))
    if not scores:
        return np.zeros(0), np.zeros(0, bool), 0
    return np.concatenate(scores), np.concatenate(tps), n_gt


def _inputs(scores_or_matches, tp, n_gt, label):
    is_matches = isinstance(scores_or_matches, FrameMatch) or (
        isinstance(scores_or_matches, Sequence) and len(scores_or_matches) > 0
        and all(isinstance(x, FrameMatch) for x in scores_or_matches))
    if is_matches:
        if tp is not None or n_gt is not None:
            raise ValueError("pass either FrameMatch objects or scores, tp and n_gt")
        return _gather(scores_or_matches, label)
    if tp is None or n_gt is None:
        raise ValueError("scores need tp and n_gt")
    if label is not None:
        raise ValueError("label applies to FrameMatch input only")
    s = _scores(scores_or_matches, np.asarray(scores_or_matches).size, "scores")
    t = _tp_array(tp, len(s))
    if int(n_gt) != n_gt or n_gt < 0:
        raise ValueError(f"n_gt must be a non-negative integer, got {n_gt}")
    n_gt = int(n_gt)
    if np.count_nonzero(t) > n_gt:
        raise ValueError(f"{np.count_nonzero(t)} TPs exceed n_gt = {n_gt}")
    return s, t, n_gt


def precision_recall(scores_or_matches, tp=None, n_gt=None, *, label=None):
    """``(precision, recall, score_thresholds)`` at each distinct score, descending.

    Input as for ``average_precision``. Recall is ``nan`` when ``n_gt == 0``.
    """
    s, t, n = _inputs(scores_or_matches, tp, n_gt, label)
    ctp, cdet, thr = _curve(s, t)
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = ctp / n if n else np.full(len(ctp), np.nan)
    return ctp / cdet, recall, thr


_NAMED_LEVELS = {40: (np.arange(1, 41), 40), 11: (np.arange(0, 11), 10),
                 101: (np.arange(0, 101), 100)}


def average_precision(scores_or_matches, tp=None, n_gt=None, *, recall_points=40,
                      label=None) -> float:
    """Interpolated AP (module docstring): R40 by default, R11 with ``recall_points=11``.

    Input: a FrameMatch or list of them (non-ignored detections and GT boxes, of class
    ``label`` if given), or arrays ``scores``, ``tp`` plus the number of GT boxes ``n_gt``.
    ``recall_points`` is 40, 11, 101 or an explicit array of recall levels in [0, 1].
    Returns ``nan`` when ``n_gt == 0``.
    """
    s, t, n = _inputs(scores_or_matches, tp, n_gt, label)
    if n == 0:
        return float("nan")
    ctp, cdet, _ = _curve(s, t)
    # max precision over all later points: the points with recall >= r form a suffix
    best = np.maximum.accumulate((ctp / np.maximum(cdet, 1))[::-1])[::-1]
    best = np.r_[best, 0.0]  # recall level not reached: precision 0
    if isinstance(recall_points, (int, np.integer)):
        if int(recall_points) not in _NAMED_LEVELS:
            raise ValueError(f"recall_points must be 40, 11, 101 or an array, got {recall_points}")
        k, big_k = _NAMED_LEVELS[int(recall_points)]
        # recall >= k / K  <=>  ctp * K >= k * n (exact integers)
        first = np.searchsorted(ctp * big_k, k * n, side="left")
    else:
        r = np.asarray(recall_points, dtype=np.float64).reshape(-1)
        if not len(r) or not np.all((r >= 0) & (r <= 1)):
            raise ValueError("recall levels must be a non-empty array in [0, 1]")
        first = np.searchsorted(ctp / n, r - 1e-12, side="left")
    return float(best[first].mean())


# ------------------------------------------------------------------------ summaries
def summarize(matches: Sequence[FrameMatch], classes=None, *, recall_points=40) -> dict:
    """Per-class AP and counts from existing matches; mAP over classes that have GT.

    ``classes`` defaults to all detection and GT classes, in order of appearance.
    Returns ``{"per_class": {c: {"ap", "n_gt", "n_det", "n_tp", "n_fp", "n_ignored"}},
    "map", "map_classes", "recall_points"}``; ``ap`` is ``nan`` for a class without GT.
    """
    matches = list(matches)
    if classes is None:
        seen: dict[Any, None] = {}
        for fm in matches:
            seen.update(dict.fromkeys(fm.gt_labels.tolist()))
            seen.update(dict.fromkeys(fm.labels.tolist()))
        classes = list(seen)
    per_class = {}
    for c in classes:
        n_det = n_tp = n_ign = 0
        for fm in matches:
            sel = fm.labels == c
            n_det += int(np.count_nonzero(sel))
            n_tp += int(np.count_nonzero(fm.tp & sel))
            n_ign += int(np.count_nonzero(fm.ignored & sel))
        s, t, n_gt = _gather(matches, c)
        ap = average_precision(s, t, n_gt, recall_points=recall_points)
        per_class[c] = {"ap": ap, "n_gt": n_gt, "n_det": n_det, "n_tp": n_tp,
                        "n_fp": n_det - n_tp - n_ign, "n_ignored": n_ign}
    in_map = [c for c in classes if per_class[c]["n_gt"] > 0]
    m_ap = float(np.mean([per_class[c]["ap"] for c in in_map])) if in_map else float("nan")
    return {"per_class": per_class, "map": m_ap, "map_classes": in_map,
            "recall_points": recall_points}


_FRAME_KEYS = ("det_boxes", "det_scores", "det_labels", "gt_boxes", "gt_labels", "gt_ignore")


def _frame_kwargs(frame) -> dict:
    if isinstance(frame, Mapping):
        unknown = set(frame) - set(_FRAME_KEYS)
        if unknown:
            raise ValueError(f"unknown frame keys {sorted(unknown)}; expected {_FRAME_KEYS}")
        return dict(frame)
    frame = tuple(frame)
    if len(frame) not in (5, 6):
        raise ValueError(f"a frame tuple needs 5 or 6 items {_FRAME_KEYS}, got {len(frame)}")
    return dict(zip(_FRAME_KEYS, frame))


def evaluate(frames, classes, iou_thresholds, mode: str = "bev", *, recall_points=40,
             strict: bool = False) -> dict:
    """Match every frame, then ``summarize``; the result also holds ``"matches"``.

    ``frames``: dicts with the ``match_frame`` argument names (``det_boxes``,
    ``det_scores``, ``det_labels``, ``gt_boxes``, ``gt_labels``, optional ``gt_ignore``)
    or tuples in that order. ``iou_thresholds``: one value or a dict class -> threshold.
    """
    matches = [match_frame(**_frame_kwargs(f), iou_threshold=iou_thresholds, mode=mode,
                           strict=strict) for f in frames]
    out = summarize(matches, classes, recall_points=recall_points)
    out.update(mode=mode, iou_thresholds=iou_thresholds, strict=strict, matches=matches)
    return out


# ----------------------------------------------------------------------- partitions
class Partition(IntEnum):
    """Detection partition codes of ``fp_partition``."""

    IGNORED = -1
    TP = 0
    FP_ML = 1
    FP_BG = 2
    DUPLICATE = 3


def fp_partition(match: FrameMatch, *, bg_iou: float = MIMO_BG_IOU,
                 separate_duplicates: bool = False) -> np.ndarray:
    """(N,) int8 ``Partition`` codes: TP / FP_ML / FP_BG per LiDAR-MIMO (module docstring).

    TP = ``match.tp``; FP_BG iff ``iou_any <= bg_iou`` (all GT boxes, any class); FP_ML
    otherwise. ``separate_duplicates`` labels duplicates DUPLICATE instead of FP_ML.
    Detections that matched an ignored GT box are IGNORED.
    """
    out = np.full(len(match.tp), Partition.FP_ML, dtype=np.int8)
    out[match.iou_any <= bg_iou] = Partition.FP_BG
    if separate_duplicates:
        out[match.hit(class_aware=True) & ~match.tp] = Partition.DUPLICATE
    out[match.tp] = Partition.TP
    out[match.ignored] = Partition.IGNORED
    return out


def partition_counts(matches, **kwargs) -> dict[str, int]:
    """Counts of each ``Partition`` over one or several frames (``fp_partition`` kwargs)."""
    if isinstance(matches, FrameMatch):
        matches = [matches]
    codes = [fp_partition(fm, **kwargs) for fm in matches]
    allc = np.concatenate(codes) if codes else np.zeros(0, np.int8)
    return {p.name: int(np.count_nonzero(allc == p)) for p in Partition}
