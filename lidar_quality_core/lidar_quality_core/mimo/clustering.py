"""LiDAR-MIMO clustering of the heads' boxes (paper III.C), numpy / scipy only.

The K heads' post-NMS boxes of a frame, pooled, are clustered by DBSCAN; each cluster is
then merged by :mod:`lidar_quality_core.mimo.merging`. Choices (method-details.md,
LiDAR-MIMO, = the authors' code mpitropov/uncertainty_eval ``cluster.py`` unless marked
"ours"):

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
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from lidar_quality_core.box_geometry import as_boxes
from lidar_quality_core.iou import iou_bev_pairs

__all__ = ["VOTING_RULES", "DBSCAN_IMPLS", "min_cluster_size", "neighbour_pairs",
           "valid_neighbour_pairs", "dbscan_pairs", "dbscan_sklearn"]

VOTING_RULES = ("affirmative", "consensus", "unanimous")
DBSCAN_IMPLS = ("own", "sklearn")


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
        return valid_neighbour_pairs(boxes, eps, labels)
    vi = np.flatnonzero(valid)
    i, j = valid_neighbour_pairs(boxes[vi], eps, None if labels is None else labels[vi])
    return vi[i], vi[j]


def valid_neighbour_pairs(boxes, eps, labels):
    """:func:`neighbour_pairs` of boxes known to be valid (finite, l and w > 0)."""
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
