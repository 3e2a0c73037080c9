"""LiDAR-MIMO clustering of the heads' boxes (paper III.C).

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
  passes only the undecided ones (IoU near 1 - eps) to ``iou_bev_indexed``; its pairs equal
  those of thresholding ``sparse_iou`` (tested). Candidates and bounds are one compiled
  sweep over the boxes sorted by x (``_bounded_pairs``): as ~50 numpy steps they cost a
  MIMO frame 0.35 ms, most of it per-step overhead on a few hundred pairs.
* Our DBSCAN (``dbscan="own"``, default) gives exactly scikit-learn's labels (cluster ids
  in order of their first core point; a border point joins the first such cluster it
  touches; tested against it), from the sparse neighbour pairs by a compiled union-find
  over core-core pairs. ``dbscan="sklearn"`` runs ``sklearn.cluster.DBSCAN(metric=
  "precomputed")`` on the dense distance matrix. Measured on the benchmark frames
  (bench/bench_mimo_merge.py ``mimo.dbscan_*``; one thread, 2 shared cores; the
  clustering step alone, from the neighbour pairs), a fresh-clone bench of 2026-12-06:
  K=2 x 100 boxes: own 0.004 ms, sklearn 1.76 ms; K=4 x 100: own 0.008 ms, sklearn
  2.54 ms (as a numpy chain of min-label propagation, own took 0.055 and 0.067 ms; a
  sparse precomputed matrix for sklearn, tried once, 2.11 and 2.52 ms). Own it is
  (sklearn's per-call overhead dominates at n <= 400).
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from lidar_quality_core.box_geometry import as_boxes
from lidar_quality_core.iou import iou_bev_indexed
from lidar_quality_core.kernel_types import I1, array_in, array_out

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


# helpers inlined into the kernel: a call to a function compiled on its own costs ~80 ns
@njit(inline="always")
def _overlap(half_a, c, half_b):
    """Overlap length of [-half_a, half_a] and [c - half_b, c + half_b]."""
    return max(min(half_a, c + half_b) - max(-half_a, c - half_b), 0.0)


@njit(inline="always")
def _frame_bounds(dx, dy, ca, sa, hl, hw, bl, bw, C, S):
    # Bounds on the BEV intersection of boxes a, b from a's frame (b's centre at dx, dy
    # from a's; half sizes hl, hw of a, bl, bw of b): upper = a against b's bounding
    # rectangle in a's frame; lower = a against the a-aligned rectangle inscribed in b
    # (half sizes p, q with p C + q S = bl, p S + q C = bw), or 0 without one.
    u, v = ca * dx + sa * dy, ca * dy - sa * dx
    upper = _overlap(hl, u, bl * C + bw * S) * _overlap(hw, v, bl * S + bw * C)
    det = C * C - S * S
    if det <= 1e-9:
        return upper, 0.0
    p, q = (C * bl - S * bw) / det, (C * bw - S * bl) / det
    if not (p > 0 and q > 0):
        return upper, 0.0
    return upper, _overlap(hl, u, p) * _overlap(hw, v, q)


@njit(types.Tuple((types.int64[::1], types.int64[::1], types.int8[::1]))(
    array_in(types.float64, 2), array_in(types.float64), array_in(types.float64),
    array_in(types.float64), array_in(types.int64), array_in(types.int64), types.boolean,
    types.float64), cache=True, nogil=True)
def _bounded_pairs(boxes, c, s, r, order, labels, use_labels, t):
    # Pairs i < j whose centres lie within r_i + r_j (the half diagonals), found by a sweep
    # over ``order`` (x ascending), each decided by the bounds: 1 = neighbours, 0 =
    # undecided (the exact IoU decides). IoU = I / (A_a + A_b - I) grows with I, so bounds
    # on I bound the IoU; the 1e-9 margin leaves every pair near the threshold undecided.
    n = len(order)
    cap = 4 * n + 16
    oi = np.empty(cap, np.int64)
    oj = np.empty(cap, np.int64)
    state = np.empty(cap, np.int8)
    k = 0
    rmax2 = 2.0 * r.max() if n else 0.0
    for a in range(n):
        i0 = order[a]
        for b in range(a + 1, n):
            j0 = order[b]
            if boxes[j0, 0] - boxes[i0, 0] > rmax2:
                break
            i, j = (i0, j0) if i0 < j0 else (j0, i0)
            dx, dy = boxes[j, 0] - boxes[i, 0], boxes[j, 1] - boxes[i, 1]
            if not dx * dx + dy * dy <= (r[i] + r[j]) ** 2:
                continue
            if use_labels and labels[i] != labels[j]:
                continue
            ca, sa, cb, sb = c[i], s[i], c[j], s[j]
            C, S = abs(ca * cb + sa * sb), abs(sb * ca - cb * sa)  # |cos|, |sin| of the yaw gap
            hli, hwi, hlj, hwj = boxes[i, 3] / 2, boxes[i, 4] / 2, boxes[j, 3] / 2, boxes[j, 4] / 2
            up_i, lo_i = _frame_bounds(dx, dy, ca, sa, hli, hwi, hlj, hwj, C, S)
            up_j, lo_j = _frame_bounds(-dx, -dy, cb, sb, hlj, hwj, hli, hwi, C, S)
            area_i, area_j = boxes[i, 3] * boxes[i, 4], boxes[j, 3] * boxes[j, 4]
            up = min(min(up_i, up_j), min(area_i, area_j))
            lo = max(lo_i, lo_j)
            tot = area_i + area_j
            if lo >= (t + 1e-9) * (tot - lo):
                st = 1
            elif up >= (t - 1e-9) * (tot - up):
                st = 0
            else:
                continue
            if k == cap:
                cap *= 2
                oi2, oj2, st2 = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int8)
                oi2[:k], oj2[:k], st2[:k] = oi[:k], oj[:k], state[:k]
                oi, oj, state = oi2, oj2, st2
            oi[k], oj[k], state[k] = i, j, st
            k += 1
    return oi[:k].copy(), oj[:k].copy(), state[:k].copy()


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
    boxes = np.ascontiguousarray(boxes, dtype=np.float64)
    r = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    # any label values (names, ids): equal labels, equal codes
    lab = (np.zeros(0, np.int64) if labels is None
           else np.unique(np.asarray(labels), return_inverse=True)[1].astype(np.int64).reshape(-1))
    return _neighbours(boxes, c, s, r, np.argsort(boxes[:, 0], kind="stable"), lab,
                       labels is not None, float(eps))


@njit(types.UniTuple(array_out(types.int64), 2)(
    array_in(types.float64, 2), array_in(types.float64), array_in(types.float64),
    array_in(types.float64), I1, I1, types.boolean, types.float64), cache=True, nogil=True)
def _neighbours(boxes, c, s, r, order, labels, use_labels, eps):
    """:func:`valid_neighbour_pairs`' pairs in one compiled call: those the bounds decide
    (``_bounded_pairs``) and the undecided ones whose exact IoU is at least ``1 - eps``
    (the boxes are valid, their trig is known); a numpy chain of ~12 calls before."""
    i, j, st = _bounded_pairs(boxes, c, s, r, order, labels, use_labels, 1.0 - eps)
    keep = st == 1
    undecided = np.flatnonzero(st == 0)
    if undecided.shape[0]:
        iou = iou_bev_indexed(boxes, i[undecided], j[undecided], c, s)
        for p in range(undecided.shape[0]):
            if 1.0 - iou[p] <= eps:
                keep[undecided[p]] = True
    return i[keep], j[keep]


def dbscan_pairs(n: int, i: np.ndarray, j: np.ndarray, min_samples: int) -> np.ndarray:
    """DBSCAN labels (-1 noise) of ``n`` points from their neighbour pairs ``i < j``; the
    same labels as scikit-learn's DBSCAN on the matching distance matrix."""
    i = np.ascontiguousarray(i, np.int64).reshape(-1)
    j = np.ascontiguousarray(j, np.int64).reshape(-1)
    if len(i) != len(j):
        raise ValueError(f"{len(i)} pair starts for {len(j)} pair ends")
    lab, ok = _dbscan(int(n), i, j, int(min_samples))
    if not ok:
        raise ValueError(f"neighbour pairs name points outside 0..{n - 1}")
    return lab


@njit(types.Tuple((array_out(types.int64), types.boolean))(types.int64, I1, I1, types.int64),
      cache=True, nogil=True)
def _dbscan(n, i, j, min_samples):
    """``(labels, ok)``: :func:`dbscan_pairs` in one compiled pass (a numpy chain of ~30
    steps before; ``ok`` False for pairs outside ``0..n-1``). Core points: ``min_samples`` or more
    neighbours, itself included. Their connected components over core-core pairs, each
    named by its smallest index (union-find, the smaller root kept). A border point joins
    the component of smallest root among its core neighbours: sklearn expands clusters in
    index order of their first core point, so the first to reach a border point keeps it.
    Cluster id: the rank of the root in index order (sklearn's numbering)."""
    m = len(i)
    deg = np.ones(n, np.int64)
    for k in range(m):
        a, b = i[k], j[k]
        if a < 0 or a >= n or b < 0 or b >= n:
            return np.empty(0, np.int64), False
        deg[a] += 1
        deg[b] += 1
    core = deg >= min_samples
    root = np.arange(n)
    for k in range(m):
        a, b = i[k], j[k]
        if core[a] and core[b]:
            while root[a] != a:
                root[a] = root[root[a]]
                a = root[a]
            while root[b] != b:
                root[b] = root[root[b]]
                b = root[b]
            if a < b:
                root[b] = a
            elif b < a:
                root[a] = b
    lab = np.full(n, n, np.int64)   # n: no cluster
    for x in range(n):  # roots are smaller than their members: one pass in index order
        if core[x]:
            lab[x] = x if root[x] == x else lab[root[x]]
    for k in range(m):
        a, b = i[k], j[k]
        if core[a] != core[b]:
            c, x = (a, b) if core[a] else (b, a)
            if lab[c] < lab[x]:
                lab[x] = lab[c]
    rank = np.empty(n, np.int64)
    r = -1
    for x in range(n):
        if lab[x] == x:
            r += 1
        rank[x] = r
    out = np.empty(n, np.int64)
    for x in range(n):
        out[x] = rank[lab[x]] if lab[x] < n else -1
    return out, True


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
