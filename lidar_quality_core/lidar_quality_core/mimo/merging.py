"""LiDAR-MIMO merging of the clustered head outputs (paper III.C), a pure numpy module.

``merge_heads(heads, config)`` pools the post-NMS detections of the K heads of one frame,
clusters them and merges every cluster into one detection with its uncertainty
statistics (``uncertainty.py``). Choices (method-details.md, LiDAR-MIMO, = the authors'
code mpitropov/uncertainty_eval ``cluster.py`` unless marked "ours"):

* Inputs per head: boxes (n, 7) x, y, z, l, w, h, yaw; class scores (n, C) with column
  ``background_index`` the background (None: no background column), as logits or, with
  ``score_type="probabilities"``, as probabilities converted by logits = log(max(p, 1e-12))
  (ours: the floor keeps p = 0 finite; softmax renormalizes rows that do not sum to 1);
  optional predicted variances (n, 7) (missing: NaN). The reference multi-head detector's
  ``HeadOutput`` (logits = log-probabilities, column 0 background) converts with
  ``HeadDetections.from_head_output``.
* Clustering: DBSCAN on the distance 1 - rotated BEV IoU over all heads' boxes pooled
  (:mod:`lidar_quality_core.mimo.clustering`, where the choices are documented); noise
  is dropped.
* Merge ("mean"): box = member mean, yaw from the highest-confidence member (a mean of
  yaws 0 and pi would point sideways). Member confidence = its best foreground
  probability softmax(logits / T); ties go to the lowest head index. Class distribution =
  softmax(mean member logits / T) (``temperature`` T, default 1); label = its argmax over
  the foreground columns (a column index of the input), score = that probability.
* Statistics: ``uncertainty.cluster_statistics`` (SE, AE, MI in bits from the member
  distributions softmax(logits / T); ETV, ATV, per-parameter epistemic / aleatoric /
  predictive variance; yaw handling documented there: ``yaw_deviation``,
  ``yaw_variance``). The predicted variances are used as given: the authors rescale
  l, w, h variances by (cluster mean size / member size)^2 because their head encodes
  sizes as log ratios; the reference detector's variances are already in metres^2.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np
from numba import njit, types

from lidar_quality_core.box_geometry import as_boxes
from lidar_quality_core.kernel_types import F1 as _F1, F2 as _F2, I1, array_in, array_out
from lidar_quality_core.parameters import param

from .clustering import (DBSCAN_IMPLS, VOTING_RULES, dbscan_pairs, dbscan_sklearn,
                         min_cluster_size, valid_neighbour_pairs)
from .uncertainty import (GROUP_STATISTICS, YAW_DEVIATIONS, YAW_VARIANCES, ClusterStatistics,
                          group_statistics)

__all__ = ["HeadDetections", "MergeConfig", "MergeResult", "merge_heads"]

SCORE_TYPES = ("logits", "probabilities")
PROB_FLOOR = 1e-12


@dataclass(frozen=True)
class HeadDetections:
    """One head's post-NMS detections of a frame."""

    boxes: np.ndarray                     # (n, 7) x, y, z, l, w, h, yaw
    class_scores: np.ndarray              # (n, C) logits or probabilities (MergeConfig)
    variances: np.ndarray | None = None   # (n, 7) predicted variances, None: unknown

    @classmethod
    def from_head_output(cls, head) -> "HeadDetections":
        """From a ``reference_perception.multihead.HeadOutput`` (its NMS survivors)."""
        k = head.keep
        return cls(head.boxes[k], head.logits[k], head.variances[k])


@dataclass(frozen=True)
class MergeConfig:
    """Clustering and merging settings; the fields made with ``param`` are mimo_node's
    parameters (declared from here)."""

    eps: float = param(
        0.5, "DBSCAN radius on the distance 1 - rotated BEV IoU: boxes with BEV IoU >= "
        "1 - eps are neighbours.", min_value=0.0, max_value=1.0, open_min=True, open_max=True)
    voting: str = param(
        "consensus", "Minimum cluster size rule over the K heads: affirmative (1), consensus "
        "(int(K/2 + 1)) or unanimous (K).", choices=VOTING_RULES)
    min_cluster_size: int | None = param(
        0, "DBSCAN min_samples; 0: from the voting rule.", min_value=0,
        to_field=lambda v: v or None, to_param=lambda v: v or 0)   # None: the voting rule's
    class_aware: bool = param(
        False, "Cluster only boxes whose labels agree (default: class ignored, as LiDAR-MIMO).")
    score_type: str = "logits"             # logits | probabilities
    background_index: int | None = 0       # background column, None: all foreground
    temperature: float = param(
        1.0, "Temperature T of the merged class distribution softmax(mean member logits / T).",
        min_value=0.0, open_min=True)
    yaw_deviation: str = "wrapped"         # ETV of yaw: wrapped | raw (uncertainty.py)
    yaw_variance: str = "top"              # predictive yaw variance: top | mixture
    dbscan: str = "own"                    # own | sklearn (same labels)

    def __post_init__(self):
        if not 0.0 < self.eps < 1.0:
            raise ValueError(f"eps must be in (0, 1), got {self.eps}")
        if self.voting not in VOTING_RULES:
            raise ValueError(f"voting must be one of {VOTING_RULES}, got {self.voting!r}")
        if self.min_cluster_size is not None and self.min_cluster_size < 1:
            raise ValueError(f"min_cluster_size must be >= 1, got {self.min_cluster_size}")
        if self.score_type not in SCORE_TYPES:
            raise ValueError(f"score_type must be one of {SCORE_TYPES}, got {self.score_type!r}")
        if not self.temperature > 0.0:
            raise ValueError(f"temperature must be > 0, got {self.temperature}")
        if self.yaw_deviation not in YAW_DEVIATIONS:
            raise ValueError(f"yaw_deviation must be one of {YAW_DEVIATIONS}")
        if self.yaw_variance not in YAW_VARIANCES:
            raise ValueError(f"yaw_variance must be one of {YAW_VARIANCES}")
        if self.dbscan not in DBSCAN_IMPLS:
            raise ValueError(f"dbscan must be one of {DBSCAN_IMPLS}, got {self.dbscan!r}")

    def min_samples(self, num_heads: int) -> int:
        if self.min_cluster_size is not None:
            return int(self.min_cluster_size)
        return min_cluster_size(self.voting, num_heads)


@dataclass
class MergeResult:
    """Merged detections of one frame (C clusters) and where their members came from
    (M pooled input boxes, head after head)."""

    boxes: np.ndarray            # (C, 7) member mean, yaw of the top member
    class_probs: np.ndarray      # (C, ncls) softmax(mean member logits / T)
    labels: np.ndarray           # (C,) class column (never the background column)
    scores: np.ndarray           # (C,) class_probs at labels
    stats: ClusterStatistics     # per-cluster statistics (uncertainty.py)
    top_member: np.ndarray       # (C,) pooled row of each cluster's top member
    member_head: np.ndarray      # (M,) head of each pooled box
    member_index: np.ndarray     # (M,) its row within that head
    member_cluster: np.ndarray   # (M,) its cluster, -1: noise or invalid
    num_heads: int = 0           # K
    min_samples: int = 1         # DBSCAN min_samples used

    def __len__(self) -> int:
        return len(self.boxes)

    def head_fraction(self, num_heads: int | None = None) -> np.ndarray:
        """(C,) distinct heads among each cluster's members / ``num_heads`` (default K)."""
        k = max(self.num_heads if num_heads is None else int(num_heads), 1)
        out, ok = _head_fraction(np.ascontiguousarray(self.member_cluster, np.int64),
                                 np.ascontiguousarray(self.member_head, np.int64), len(self), k)
        if not ok:
            raise ValueError(f"members name clusters outside 0..{len(self) - 1} or heads "
                             f"outside 0..{k - 1}")
        return out

    def members(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """``(head, index)`` arrays of cluster ``c``'s members."""
        m = self.member_cluster == c
        return self.member_head[m], self.member_index[m]


# ------------------------------------------------------------------ merging
@lru_cache(maxsize=32)
def _foreground(n_cls: int, background_index: int | None) -> np.ndarray:
    """The foreground columns' mask (read-only: shared by the frames of a config)."""
    fg = np.ones(n_cls, bool)
    if background_index is not None and n_cls:
        fg[background_index] = False
    fg.flags.writeable = False
    return fg


@njit(types.UniTuple(array_out(types.intp), 2)(I1), cache=True, nogil=True)
def _member_rows(lengths):
    """Per pooled member its head and its row in that head (heads of ``lengths`` rows)."""
    m = 0
    for k in range(lengths.shape[0]):
        m += lengths[k]
    head = np.empty(m, np.intp)
    index = np.empty(m, np.intp)
    at = 0
    for k in range(lengths.shape[0]):
        for r in range(lengths[k]):
            head[at], index[at] = k, r
            at += 1
    return head, index


@njit(types.Tuple((array_out(types.int64), array_out(types.float64, 2),
                   array_out(types.float64, 2), array_out(types.float64, 2),
                   array_out(types.float64, 2)))(_F2, _F2, _F2, types.float64),
      cache=True, nogil=True)
def _members(boxes, logits, var, temperature):
    """``(vi, boxes, logits, variances, t)`` of the valid members: their rows, and ``t``
    (C, n) = their logits / T minus each member's largest, class-major: the softmax's
    steps before its exponential, as numpy's class-major ``z / T - max`` gave them (one
    compiled pass: ~20 numpy calls before). Valid: l and w > 0, and the box's and the
    logits' sums (in column order) finite, i.e. every entry finite and no overflow."""
    m_all, n_cls = logits.shape
    keep = np.empty(m_all, np.int64)
    n = 0
    for m in range(m_all):
        box_sum, logit_sum = 0.0, 0.0
        for k in range(7):
            box_sum += boxes[m, k]
        for c in range(n_cls):
            logit_sum += logits[m, c]
        if (np.isfinite(box_sum) and boxes[m, 3] > 0 and boxes[m, 4] > 0
                and np.isfinite(logit_sum)):
            keep[n] = m
            n += 1
    vi = keep[:n].copy()
    b, v = np.empty((n, 7)), np.empty((n, 7))
    lg, t = np.empty((n, n_cls)), np.empty((n_cls, n))
    for r in range(n):
        m = vi[r]
        for k in range(7):
            b[r, k] = boxes[m, k]
            v[r, k] = var[m, k]
        hi = -np.inf
        for c in range(n_cls):
            x = logits[m, c]
            lg[r, c] = x
            if temperature != 1.0:
                x /= temperature
            t[c, r] = x
            if hi == hi and not x <= hi:  # numpy's maximum: a NaN, once met, stays
                hi = x
        for c in range(n_cls):
            t[c, r] -= hi
    return vi, b, lg, v, t


@njit(types.Tuple((array_out(types.float64, 2), array_out(types.int64),
                   array_out(types.float64)))(_F2, array_in(types.boolean)),
      cache=True, nogil=True)
def _normalised(e, fg):
    """``(probs (n, C), label, score)`` from ``e`` = exp(:func:`_members`' ``t``): each
    member's distribution (``e`` over its sum, summed class after class as numpy's
    class-major sum), its foreground argmax (numpy's: the first largest, a NaN first
    of all) and that probability."""
    n_cls, n = e.shape
    probs = np.empty((n, n_cls))
    label = np.empty(n, np.int64)
    score = np.empty(n)
    for r in range(n):
        s = e[0, r]
        for c in range(1, n_cls):
            s += e[c, r]
        for c in range(n_cls):
            probs[r, c] = e[c, r] / s
        best = 0
        top = probs[r, 0] if fg[0] else -1.0
        if top == top:
            for c in range(1, n_cls):
                x = probs[r, c] if fg[c] else -1.0
                if not x <= top:
                    best, top = c, x
                    if x != x:
                        break
        label[r] = best
        score[r] = probs[r, best]
    return probs, label, score


def _pool(heads):
    """Stack the heads: boxes (M, 7), scores (M, C), variances (M, 7), head, index."""
    parts = []
    for k, h in enumerate(heads):
        if isinstance(h, HeadDetections):
            b, s, v = h.boxes, h.class_scores, h.variances
        else:
            b, s, v = (tuple(h) + (None,))[:3]
        b = as_boxes(b)
        s = np.asarray(s, np.float64)
        if s.ndim == 1 and s.size == 0:
            s = None  # an empty head given as []: C comes from the other heads
        elif s.ndim != 2 or len(s) != len(b) or (len(b) and s.shape[1] == 0):
            raise ValueError(f"head {k}: class scores must have shape ({len(b)}, C >= 1), "
                             f"got {s.shape}")
        v = np.full((len(b), 7), np.nan) if v is None else np.asarray(v, np.float64)
        if v.size == 0:
            v = v.reshape(0, 7)
        if v.shape != (len(b), 7):
            raise ValueError(f"head {k}: variances must have shape ({len(b)}, 7), got {v.shape}")
        parts.append((b, s, v))
    shapes = [s.shape[1] for b, s, _ in parts if s is not None and len(b)]
    if len(set(shapes)) > 1:
        raise ValueError(f"heads disagree on the number of class columns: {shapes}")
    if not shapes:  # no detections: take C from any 2-D (0, C) input
        shapes = [s.shape[1] for _, s, _ in parts if s is not None] or [0]
    ncls = shapes[0]
    if not parts:
        z = np.zeros(0, np.intp)
        return np.zeros((0, 7)), np.zeros((0, ncls)), np.zeros((0, 7)), z, z.copy()
    return (np.concatenate([b for b, _, _ in parts]),
            np.concatenate([s if s is not None and len(b) else np.zeros((0, ncls))
                            for b, s, _ in parts]),
            np.concatenate([v for _, _, v in parts]),
            *_member_rows(np.array([len(b) for b, _, _ in parts], np.int64)))


def merge_heads(heads: Sequence, config: MergeConfig = MergeConfig(), *,
                num_heads: int | None = None) -> MergeResult:
    """Cluster and merge the detections of one frame's heads.

    ``heads``: one ``HeadDetections`` (or ``(boxes, class_scores[, variances])``) per head;
    a head without detections is an empty one, never left out, since K sets the voting
    rule (``num_heads`` overrides K = ``len(heads)``).
    """
    cfg = config
    K = len(heads) if num_heads is None else int(num_heads)
    boxes, scores, var, mhead, midx = _pool(heads)
    M, ncls = scores.shape
    min_samples = cfg.min_samples(max(K, 1))
    if cfg.background_index is not None and M and not 0 <= cfg.background_index < ncls:
        raise ValueError(f"background_index {cfg.background_index} outside {ncls} columns")
    fg = _foreground(ncls, cfg.background_index)
    logits = np.log(np.maximum(scores, PROB_FLOOR)) if cfg.score_type == "probabilities" else scores
    vi, boxes, logits, var, t = _members(boxes, logits, var, float(cfg.temperature))
    member_cluster = np.full(M, -1, np.intp)
    if len(vi) == 0 or not fg.any():
        return _empty_result(ncls, mhead, midx, member_cluster, K, min_samples)
    np.exp(t, out=t)
    probs, member_label, member_score = _normalised(t, fg)
    i, j = valid_neighbour_pairs(boxes, cfg.eps, member_label if cfg.class_aware else None)
    if cfg.dbscan == "own":
        lab = dbscan_pairs(len(vi), i, j, min_samples)
    else:
        lab = dbscan_sklearn(len(vi), i, j, min_samples, cfg.eps)
    member_cluster[vi] = lab

    if not (lab >= 0).any():
        return _empty_result(ncls, mhead, midx, member_cluster, K, min_samples)
    order, top, merged, cls_probs, labels, scores, stats = _merged(
        boxes, logits, var, probs, np.ascontiguousarray(lab, np.int64), member_score, fg,
        float(cfg.temperature), cfg.yaw_deviation == "wrapped", cfg.yaw_variance == "top")
    return MergeResult(boxes=merged, class_probs=cls_probs, labels=labels, scores=scores,
                       stats=ClusterStatistics(*stats), top_member=vi[order[top]],
                       member_head=mhead, member_index=midx, member_cluster=member_cluster,
                       num_heads=K, min_samples=min_samples)


@njit(types.Tuple((array_out(types.float64), types.boolean))(I1, I1, types.int64, types.int64),
      cache=True, nogil=True)
def _head_fraction(cluster, head, n_clusters, k):
    """``(fraction, ok)`` of :meth:`MergeResult.head_fraction` in one compiled pass (a
    unique and a bincount before); ``ok`` False for a member outside the clusters / heads."""
    seen = np.zeros(n_clusters * k, np.bool_)
    count = np.zeros(n_clusters, np.int64)
    for m in range(len(cluster)):
        c = cluster[m]
        if c < 0:
            continue
        h = head[m]
        if c >= n_clusters or h < 0 or h >= k:
            return np.empty(0), False
        if not seen[c * k + h]:
            seen[c * k + h] = True
            count[c] += 1
    return count / k, True


_MERGED_OUT = types.Tuple((array_out(types.int64), array_out(types.int64),
                           array_out(types.float64, 2), array_out(types.float64, 2),
                           array_out(types.int64), array_out(types.float64), GROUP_STATISTICS))


@njit(_MERGED_OUT(_F2, _F2, _F2, _F2, array_in(types.int64), _F1, array_in(types.boolean),
                  types.float64, types.boolean, types.boolean), cache=True, nogil=True)
def _merged(boxes, logits, var, probs, lab, member_score, fg, temperature, wrapped, top_yaw):
    """The merge of the clustered members (``lab`` >= 0) in one compiled pass (module
    doc): ``(order, top, boxes, class_probs, labels, scores, statistics)``; ``order``:
    the members grouped cluster after cluster, highest confidence first (ties: lowest
    row, as np.lexsort), ``top``: each group's first row in ``order``. Sums run member
    after member as numpy's grouped sums did; the numpy chain it replaces was ~40 calls
    a frame, each far dearer than its arithmetic. At least one member is clustered."""
    keep = np.flatnonzero(lab >= 0)
    by_score = keep[np.argsort(-member_score[keep], kind="mergesort")]
    order = by_score[np.argsort(lab[by_score], kind="mergesort")]
    n = order.shape[0]
    starts = np.empty(n, np.int64)
    starts[0] = 0
    n_groups = 1
    for r in range(1, n):
        if lab[order[r]] != lab[order[r - 1]]:
            starts[n_groups] = r
            n_groups += 1
    top = starts[:n_groups].copy()
    gb, gl, gv, gp = boxes[order], logits[order], var[order], probs[order]
    ncls = logits.shape[1]
    merged = np.zeros((n_groups, 7))
    cls_probs = np.zeros((n_groups, ncls))
    labels = np.empty(n_groups, np.int64)
    scores = np.empty(n_groups)
    for g in range(n_groups):
        a = top[g]
        b = top[g + 1] if g + 1 < n_groups else n
        for r in range(a, b):
            for k in range(7):
                merged[g, k] += gb[r, k]
            for c in range(ncls):
                cls_probs[g, c] += gl[r, c]
        m = np.float64(b - a)
        for k in range(7):
            merged[g, k] /= m
        merged[g, 6] = gb[a, 6]
        # softmax(mean logits / T), as _members and _normalised for the members
        hi = -np.inf
        for c in range(ncls):
            cls_probs[g, c] /= m
            if temperature != 1.0:
                cls_probs[g, c] /= temperature
            hi = max(hi, cls_probs[g, c])
        total = 0.0
        for c in range(ncls):
            cls_probs[g, c] = np.exp(cls_probs[g, c] - hi)
            total += cls_probs[g, c]
        best, best_c = -np.inf, 0
        for c in range(ncls):
            cls_probs[g, c] /= total
            v = cls_probs[g, c] if fg[c] else -1.0
            if v > best:
                best, best_c = v, c
        labels[g] = best_c
        scores[g] = cls_probs[g, best_c]
    stats = group_statistics(gp, gb, gv, top, top, wrapped, top_yaw)
    return order, top, merged, cls_probs, labels, scores, stats


def _empty_result(ncls, mhead, midx, member_cluster, K, min_samples) -> MergeResult:
    return MergeResult(boxes=np.zeros((0, 7)), class_probs=np.zeros((0, ncls)),
                       labels=np.zeros(0, np.intp), scores=np.zeros(0),
                       stats=ClusterStatistics.empty(), top_member=np.zeros(0, np.intp),
                       member_head=mhead, member_index=midx, member_cluster=member_cluster,
                       num_heads=K, min_samples=min_samples)
