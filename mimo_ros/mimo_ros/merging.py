"""LiDAR-MIMO output clustering and merging (paper III.C), a pure numpy module.

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
* Clustering: DBSCAN on the distance 1 - rotated BEV IoU (``lidar_quality_core.iou``)
  over all heads' boxes pooled, neighbours at distance <= ``eps`` (default 0.5),
  ``min_samples`` = the voting rule's minimum cluster size: affirmative 1, consensus
  int(K/2 + 1) (default), unanimous K. Noise is dropped. Class is ignored (authors);
  ``class_aware=True`` (ours) keeps boxes of different member labels out of each other's
  neighbourhood. Boxes of one head may share a cluster, so a cluster can exceed K members
  (DBSCAN semantics, as the authors'). Invalid members (a non-finite box value or logit,
  l or w <= 0) are noise (ours; a probability 0 is fine as a probability, not as a -inf
  logit). ``eps`` must lie in (0, 1): at 1, boxes that do not overlap at all would be
  neighbours.
* Pairwise distances: only the pairs at distance <= eps matter, and one call of the core
  IoU costs ~0.45 ms plus ~1 us a pair (measured), most of the merge. ``neighbour_pairs``
  therefore decides most pairs with cheap, exact bounds on the intersection area and
  passes only the undecided ones (IoU near 1 - eps) to ``iou_bev_pairs``; its pairs equal
  those of thresholding ``sparse_iou`` (tested).
* Our DBSCAN (``dbscan="own"``, default) gives exactly scikit-learn's labels (cluster ids
  in order of their first core point; a border point joins the first such cluster it
  touches; tested against it), from the sparse neighbour pairs by min-label propagation
  over core-core pairs. ``dbscan="sklearn"`` runs ``sklearn.cluster.DBSCAN(metric=
  "precomputed")`` on the dense distance matrix. Measured on the benchmark frames
  (bench/bench_mimo_merge.py ``mimo.dbscan_*``; one thread, 2 shared cores; the
  clustering step alone, from the neighbour pairs; medians of 3 runs of 100 calls):
  K=2 x 100 boxes: own 0.055 ms, sklearn 1.68 ms; K=4 x 100: own 0.067 ms, sklearn
  2.68 ms. An interleaved run on a busy machine also tried a sparse precomputed matrix:
  K=2 own 0.059, sklearn dense 1.67, sparse 2.11 ms; K=4 own 0.095, dense 3.93, sparse
  2.52 ms. Own it is (25-40x faster; sklearn's per-call overhead dominates at n <= 400).
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
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from lidar_quality_core.box_geometry import as_boxes
from lidar_quality_core.iou import iou_bev_pairs

from .uncertainty import YAW_DEVIATIONS, YAW_VARIANCES, ClusterStatistics, cluster_statistics

__all__ = ["VOTING_RULES", "HeadDetections", "MergeConfig", "MergeResult", "min_cluster_size",
           "merge_heads", "dbscan_pairs", "dbscan_sklearn", "neighbour_pairs"]

VOTING_RULES = ("affirmative", "consensus", "unanimous")
SCORE_TYPES = ("logits", "probabilities")
DBSCAN_IMPLS = ("own", "sklearn")
PROB_FLOOR = 1e-12


def min_cluster_size(voting: str, num_heads: int) -> int:
    """DBSCAN ``min_samples`` of a voting rule for K = ``num_heads`` heads."""
    if num_heads < 1:
        raise ValueError(f"num_heads must be >= 1, got {num_heads}")
    if voting == "affirmative":
        return 1
    if voting == "consensus":
        return int(num_heads / 2 + 1)
    if voting == "unanimous":
        return int(num_heads)
    raise ValueError(f"voting must be one of {VOTING_RULES}, got {voting!r}")


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
    eps: float = 0.5                       # DBSCAN radius on 1 - BEV IoU, in (0, 1)
    voting: str = "consensus"              # affirmative | consensus | unanimous
    min_cluster_size: int | None = None    # overrides the voting rule when set
    class_aware: bool = False              # cluster only boxes of equal member label
    score_type: str = "logits"             # logits | probabilities
    background_index: int | None = 0       # background column, None: all foreground
    temperature: float = 1.0               # T of softmax(logits / T)
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

    def members(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """``(head, index)`` arrays of cluster ``c``'s members."""
        m = self.member_cluster == c
        return self.member_head[m], self.member_index[m]


# ------------------------------------------------------------------ DBSCAN
def _overlap(half_a, c, half_b):
    """Overlap length of [-half_a, half_a] and [c - half_b, c + half_b]."""
    return np.maximum(np.minimum(half_a, c + half_b) - np.maximum(-half_a, c - half_b), 0.0)


def _frame_bounds(a, b, ca, sa, C, S):
    """Bounds on the BEV intersection of boxes a, b from a's frame: upper = a against b's
    bounding rectangle in a's frame; lower = a against the a-aligned rectangle inscribed in
    b (half sizes p, q with p C + q S = l_b/2, p S + q C = w_b/2), or 0 without one."""
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    u, v = ca * dx + sa * dy, ca * dy - sa * dx
    hl, hw, bl, bw = a[:, 3] / 2, a[:, 4] / 2, b[:, 3] / 2, b[:, 4] / 2
    upper = _overlap(hl, u, bl * C + bw * S) * _overlap(hw, v, bl * S + bw * C)
    det = C * C - S * S
    with np.errstate(divide="ignore", invalid="ignore"):
        p, q = (C * bl - S * bw) / det, (C * bw - S * bl) / det
    ok = (det > 1e-9) & (p > 0) & (q > 0)
    p, q = np.where(ok, p, 0.0), np.where(ok, q, 0.0)
    return upper, _overlap(hl, u, p) * _overlap(hw, v, q)  # 0 where p = q = 0


def neighbour_pairs(boxes: np.ndarray, eps: float, labels: np.ndarray | None = None):
    """Pairs ``i < j`` of boxes at distance 1 - BEV IoU <= ``eps`` (of equal ``labels`` if
    given). Every valid box is also its own neighbour (not listed); invalid boxes (non-finite,
    l or w <= 0) have none.

    The IoU is ``lidar_quality_core.iou``'s, computed only for the pairs that cheap bounds
    leave undecided (a call costs ~0.45 ms plus ~1 us a pair, which dominated the merge):
    candidates from a k-d tree over the centres, then an upper and a lower bound on the
    intersection area from axis-aligned rectangles in each box's frame (the other box's
    bounding rectangle; a rectangle inscribed in it). A bound decides a pair only with a
    1e-9 margin, so the pairs equal those of thresholding ``sparse_iou`` (tested).
    """
    boxes = as_boxes(boxes)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(boxes).all(axis=1) & (boxes[:, 3] > 0) & (boxes[:, 4] > 0)
    if valid.all():
        return _valid_neighbour_pairs(boxes, eps, labels)
    vi = np.flatnonzero(valid)
    i, j = _valid_neighbour_pairs(boxes[vi], eps, None if labels is None else labels[vi])
    return vi[i], vi[j]


def _valid_neighbour_pairs(boxes, eps, labels):
    if len(boxes) < 2:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    r = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    ij = cKDTree(boxes[:, :2]).query_pairs(2.0 * float(r.max()), output_type="ndarray")
    i, j = ij[:, 0], ij[:, 1]  # i < j
    keep = (boxes[i, 0] - boxes[j, 0]) ** 2 + (boxes[i, 1] - boxes[j, 1]) ** 2 <= (r[i] + r[j]) ** 2
    if labels is not None:
        keep &= labels[i] == labels[j]
    i, j = i[keep], j[keep]
    n = len(i)
    # both frames in one pass: rows [a vs b; b vs a]
    ab, ba = np.concatenate([i, j]), np.concatenate([j, i])
    A, B = boxes[ab], boxes[ba]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    ca, sa, cb, sb = c[ab], s[ab], c[ba], s[ba]
    C, S = np.abs(ca * cb + sa * sb), np.abs(sb * ca - cb * sa)  # |cos|, |sin| of yaw_b - yaw_a
    up2, lo2 = _frame_bounds(A, B, ca, sa, C, S)
    area2 = A[:, 3] * A[:, 4]
    area_a, area_b = area2[:n], area2[n:]
    up = np.minimum(np.minimum(up2[:n], up2[n:]), np.minimum(area_a, area_b))
    lo = np.maximum(lo2[:n], lo2[n:])
    t, tot = 1.0 - eps, area_a + area_b
    # IoU = I / (A_a + A_b - I) grows with I, so bounds on I bound the IoU; the margin
    # leaves every pair within 1e-9 of the threshold to the exact IoU
    ok = lo >= (t + 1e-9) * (tot - lo)
    k = np.flatnonzero(~ok & (up >= (t - 1e-9) * (tot - up)))
    if len(k):
        ok[k[(1.0 - iou_bev_pairs(A[k], B[k])) <= eps]] = True
    return i[ok], j[ok]


def dbscan_pairs(n: int, i: np.ndarray, j: np.ndarray, min_samples: int) -> np.ndarray:
    """DBSCAN labels (-1 noise) of ``n`` points from their neighbour pairs ``i < j``; the
    same labels as scikit-learn's DBSCAN on the matching distance matrix."""
    deg = np.bincount(i, minlength=n) + np.bincount(j, minlength=n) + 1  # + itself
    core = deg >= min_samples
    none = n  # sentinel label: lab[none] = none keeps the pointer jumping in range
    lab = np.append(np.where(core, np.arange(n), none), none)
    both = core[i] & core[j]
    a, b = i[both], j[both]
    # Min-label propagation over core-core pairs, with pointer jumping: every core point
    # ends with the smallest index of its connected component.
    while len(a):
        m = np.minimum(lab[a], lab[b])
        np.minimum.at(lab, a, m)
        np.minimum.at(lab, b, m)
        lab = lab[lab]
        if np.array_equal(lab[a], lab[b]):
            break
    # Border points: the component of smallest root among their core neighbours. sklearn
    # expands clusters in root order, so the first one to reach a border point keeps it.
    one = core[i] != core[j]
    if one.any():
        c, x = np.where(core[i[one]], i[one], j[one]), np.where(core[i[one]], j[one], i[one])
        np.minimum.at(lab, x, lab[c])
    # cluster id = rank of the root (a core point labelled with itself) in index order,
    # which is sklearn's order (clusters numbered as their first core point is found)
    rank = np.cumsum(lab[:n] == np.arange(n)) - 1
    lab = lab[:n]
    return np.where(lab < none, rank[np.minimum(lab, n - 1)], -1)


def dbscan_sklearn(n: int, i: np.ndarray, j: np.ndarray, min_samples: int,
                   eps: float = 0.5) -> np.ndarray:
    """scikit-learn's DBSCAN on the dense precomputed distance matrix of ``n`` points:
    0 on the diagonal and for the neighbour pairs ``(i, j)``, 1 elsewhere (``eps`` < 1)."""
    from sklearn.cluster import DBSCAN

    if n == 0:
        return np.zeros(0, np.intp)
    d = np.ones((n, n))
    np.fill_diagonal(d, 0.0)
    d[i, j] = 0.0
    d[j, i] = 0.0
    return DBSCAN(eps=eps, min_samples=min_samples, metric="precomputed").fit_predict(d)


# ------------------------------------------------------------------ merging
def _softmax(z: np.ndarray, temperature: float = 1.0) -> np.ndarray:
    """Row softmax of ``z / temperature`` in a new array (``z`` is never written).
    Computed class-major: numpy reduces a short contiguous axis (C ~ 5) several times
    slower than a long one."""
    # A copy always: for one row (or one column) z.T is already contiguous, and
    # np.ascontiguousarray would hand back a view that the in-place steps overwrite.
    t = z.T.copy(order="C")
    if temperature != 1.0:
        t /= temperature
    t -= t.max(axis=0)
    np.exp(t, out=t)
    t /= t.sum(axis=0)
    return t.T


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
            np.concatenate([np.full(len(b), k, np.intp) for k, (b, _, _) in enumerate(parts)]),
            np.concatenate([np.arange(len(b), dtype=np.intp) for b, _, _ in parts]))


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
    fg = np.ones(ncls, bool)
    if cfg.background_index is not None and ncls:
        fg[cfg.background_index] = False
    logits = np.log(np.maximum(scores, PROB_FLOOR)) if cfg.score_type == "probabilities" else scores
    with np.errstate(invalid="ignore", over="ignore"):
        # a row sum is not finite if an entry is not (matmul: fast row sums)
        valid = (np.isfinite(boxes @ np.ones(7)) & (boxes[:, 3] > 0) & (boxes[:, 4] > 0)
                 & np.isfinite(logits @ np.ones(ncls)) if M else np.zeros(0, bool))
    vi = np.flatnonzero(valid)
    member_cluster = np.full(M, -1, np.intp)
    if len(vi) == 0 or not fg.any():
        return _empty_result(ncls, mhead, midx, member_cluster, K, min_samples)
    if len(vi) < M:
        boxes, logits, var = boxes[vi], logits[vi], var[vi]

    probs = _softmax(logits, cfg.temperature)
    member_label = np.argmax(np.where(fg, probs, -1.0), axis=1)
    member_score = np.take_along_axis(probs, member_label[:, None], axis=1)[:, 0]
    i, j = _valid_neighbour_pairs(boxes, cfg.eps, member_label if cfg.class_aware else None)
    if cfg.dbscan == "own":
        lab = dbscan_pairs(len(vi), i, j, min_samples)
    else:
        lab = dbscan_sklearn(len(vi), i, j, min_samples, cfg.eps)
    member_cluster[vi] = lab

    keep = np.flatnonzero(lab >= 0)
    if len(keep) == 0:
        return _empty_result(ncls, mhead, midx, member_cluster, K, min_samples)
    # group members cluster after cluster, highest confidence first (stable: lowest head)
    order = keep[np.lexsort((-member_score[keep], lab[keep]))]
    g = lab[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    counts = np.diff(starts, append=len(order))
    top = starts  # the first member of each group is its top member

    gb, gl = boxes[order], logits[order]
    merged = np.add.reduceat(gb, starts, axis=0) / counts[:, None]
    merged[:, 6] = gb[top, 6]
    cls_probs = _softmax(np.add.reduceat(gl, starts, axis=0) / counts[:, None], cfg.temperature)
    labels = np.argmax(np.where(fg, cls_probs, -1.0), axis=1)
    stats = cluster_statistics(probs[order], gb, var[order], starts, top,
                               yaw_deviation=cfg.yaw_deviation, yaw_variance=cfg.yaw_variance)
    return MergeResult(boxes=merged, class_probs=cls_probs, labels=labels,
                       scores=np.take_along_axis(cls_probs, labels[:, None], axis=1)[:, 0],
                       stats=stats, top_member=vi[order[top]], member_head=mhead,
                       member_index=midx, member_cluster=member_cluster, num_heads=K,
                       min_samples=min_samples)


def _empty_result(ncls, mhead, midx, member_cluster, K, min_samples) -> MergeResult:
    return MergeResult(boxes=np.zeros((0, 7)), class_probs=np.zeros((0, ncls)),
                       labels=np.zeros(0, np.intp), scores=np.zeros(0),
                       stats=ClusterStatistics.empty(), top_member=np.zeros(0, np.intp),
                       member_head=mhead, member_index=midx, member_cluster=member_cluster,
                       num_heads=K, min_samples=min_samples)
