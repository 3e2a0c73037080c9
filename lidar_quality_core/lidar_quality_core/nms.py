"""Greedy rotated non-maximum suppression with the suppression map kept."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .box_geometry import as_boxes
from .iou import sparse_iou

__all__ = ["NMSResult", "rotated_nms"]


class NMSResult(NamedTuple):
    keep: np.ndarray           # (K,) int64 survivor indices, descending score
    suppressed_by: np.ndarray  # (N,) int64: suppressing kept index, own index if kept, -1 dropped


def rotated_nms(boxes, scores, iou_threshold: float, *, score_threshold: float | None = None,
                max_output: int | None = None, iou: str = "bev", classes=None) -> NMSResult:
    """Greedy NMS: highest score first (ties by lower index); a box is suppressed by the first
    kept box whose IoU with it is ``> iou_threshold`` (equal IoU is not suppressed).

    Boxes with a NaN score or a score ``< score_threshold``, and kept boxes beyond
    ``max_output`` together with the boxes they alone suppressed, get ``suppressed_by == -1``.
    ``iou`` is ``"bev"`` or ``"3d"``; with ``classes`` only boxes of the same class suppress
    each other. The pre-image of survivor ``k`` is ``{j : suppressed_by[j] == k}``.
    """
    b = as_boxes(boxes)
    n = len(b)
    sc = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(sc) != n:
        raise ValueError(f"scores has {len(sc)} entries for {n} boxes")
    cls = None
    if classes is not None:
        cls = np.asarray(classes).reshape(-1)
        if len(cls) != n:
            raise ValueError(f"classes has {len(cls)} entries for {n} boxes")
    sup = np.full(n, -1, dtype=np.int64)
    eligible = ~np.isnan(sc)
    if score_threshold is not None:
        eligible &= sc >= score_threshold
    idx = np.flatnonzero(eligible)
    if not len(idx) or (max_output is not None and max_output <= 0):
        return NMSResult(np.zeros(0, np.int64), sup)
    order = idx[np.argsort(-sc[idx], kind="stable")]  # stable: equal scores by index
    m = len(order)

    # Overlapping pairs (i < j in score order) above the threshold, as CSR rows by i.
    i, j, v = sparse_iou(b[order], None, iou)
    over = v > iou_threshold
    if cls is not None:
        cs = cls[order]
        over &= cs[i] == cs[j]
    i, j = i[over], j[over]
    ptr = np.searchsorted(i, np.arange(m + 1))  # i is sorted (row-major pairs)

    sup_s = np.arange(m, dtype=np.int64)  # in score order; kept boxes map to themselves
    alive = np.ones(m, dtype=bool)
    # Only boxes that overlap a lower-ranked one can suppress; visit those in order.
    for r in np.flatnonzero(ptr[1:] > ptr[:-1]).tolist():
        if alive[r]:
            nb = j[ptr[r]:ptr[r + 1]]
            nb = nb[alive[nb]]
            alive[nb] = False
            sup_s[nb] = r
    kept = np.flatnonzero(alive)
    if max_output is not None and len(kept) > max_output:
        # Truncating afterwards equals stopping early: what a dropped survivor suppressed
        # could not have been suppressed by an earlier survivor.
        dropped = np.zeros(m, dtype=bool)
        dropped[kept[max_output:]] = True
        sup_s[dropped[sup_s]] = -1
        kept = kept[:max_output]
    valid = sup_s >= 0
    sup[order[valid]] = order[sup_s[valid]]
    return NMSResult(order[kept].astype(np.int64), sup)
