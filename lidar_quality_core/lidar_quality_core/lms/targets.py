"""LidarMetaSeg targets: IoU and IoU_adj of each segment (paper eq. (10), (11); numpy only).

On projected pixels only. The ground truth is projected and filled through the same map; its segments are its
8-connected components of equal class (seam periodic). K' = union of the ground-truth
segments of the segment's class that intersect it (as pixel sets of the filled image);
IoU = |k n K'|_d / |k u K'|_d. IoU_adj = |k n K'|_d / |k u (K' \\ Q)|_d with Q the
predicted segments *of the same class* meeting K' (the paper's text omits "of the same
class", but with every class Q would cover K' and IoU_adj would degenerate; MetaSeg's
code and the paper's explanation mean this one): the ground-truth pixels that other
segments of the class predict do not count against k, the missed ones still do.
IoU = 0 <=> IoU_adj = 0. 0/0 gives NaN (a segment without any counted pixel).
``ignore_label`` pixels (e.g. unlabeled) are left out of every count (delta = 0 for
the targets) and match no class.
"""
from __future__ import annotations

import numpy as np

from lidar_quality_core.lms.segment_metrics import SegmentResult
from lidar_quality_core.lms.segments import label_periodic

__all__ = ["segment_targets"]


def segment_targets(result: SegmentResult, gt_labels, ignore_label: int | None = None,
                    kept_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(iou, iou_adj)`` float64 per kept segment (the rows of ``features``), or per
    segment with ``kept_only=False``, from the ground-truth class of every point of the
    cloud ``result`` was computed from (``gt_labels`` (N,) in [0, n), or
    ``ignore_label``). See the module doc."""
    gt = np.asarray(gt_labels).reshape(-1)
    N, n = len(result.point_class), result.n_classes
    if len(gt) != N:
        raise ValueError(f"gt_labels has {len(gt)} entries, the cloud {N}")
    ign = np.zeros(N, dtype=bool) if ignore_label is None else gt == ignore_label
    if ((gt[~ign] < 0) | (gt[~ign] >= n)).any():
        raise ValueError(f"ground-truth labels outside [0, {n}) (and not ignore_label)")
    ns = result.n_segments
    rows = result.kept_ids if kept_only else np.arange(ns)
    if ns == 0:
        return np.zeros(0), np.zeros(0)
    g = np.where(ign, n, gt).astype(np.int32)        # ignored pixels: a class of their own
    G = g[result.source.reshape(-1)]
    Y = result.pred.reshape(-1)
    seg = result.segments.reshape(-1)
    d = result.delta.reshape(-1) & (G < n)
    gl, ng = label_periodic(G.reshape(result.source.shape))
    gl = gl.reshape(-1)
    match = G == Y
    inter = np.bincount(seg[d & match], minlength=ns)             # |k n K'|_d
    size = np.bincount(seg[d], minlength=ns)                       # |k|_d
    g_size = np.bincount(gl[d], minlength=ng)                      # |g|_d
    g_miss = np.bincount(gl[d & ~match], minlength=ng)             # |g \ pred == c|_d
    # (segment, gt segment) pairs that intersect with equal class: K' of each segment
    pairs = np.unique(seg[match].astype(np.int64) * ng + gl[match])
    pk, pg = np.divmod(pairs, ng)
    K = np.bincount(pk, weights=g_size[pg], minlength=ns)
    K_miss = np.bincount(pk, weights=g_miss[pg], minlength=ns)
    union = size + K - inter
    union_adj = size + K_miss
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = inter / union
        iou_adj = inter / union_adj
    return iou[rows], iou_adj[rows]
