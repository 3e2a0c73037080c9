"""The numbers of mimo_node's output messages from a merge result, in one compiled pass
(``mimo_ros.pipeline.output_messages`` writes the messages from them).

Per published detection: its foreground class scores (the merged distribution, scaled by
confidence / p(label) where the confidence is finite and p(label) > 0), its pose
covariance diagonal (x, y, z, roll, pitch, yaw: the predictive variance of x, y, z and
yaw, the epistemic one where that is NaN, roll and pitch 0); per merged detection the
seven figures of the uncertainty message. The numpy chain it replaces was ~40 calls a
frame (masks, a division, a product, fancy indexing and a column stack), each dearer than
its arithmetic once a node's caches have gone cold between frames; the arithmetic is the
same, so are the bits.
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from lidar_quality_core.kernel_types import F1, F2, I1, array_out

__all__ = ["output_tables"]

_XYZYAW = (0, 1, 2, 6)   # box parameters on the covariance diagonal ...
_COV_AT = (0, 1, 2, 5)   # ... at x, y, z, yaw of the 6 pose parameters


def output_tables(merge, confidence, predicted_iou, rows, *, scale: bool):
    """``(class scores (R, C-1), covariance diagonal (R, 6), figures (n, 7))`` of a
    ``MergeResult`` with ``n`` merged detections: the published ones are ``rows`` (R,);
    ``scale``: the class scores scaled to the confidence (``output_scores: confidence``).
    Figures: Shannon entropy, aleatoric entropy, mutual information, ETV, ATV,
    confidence, predicted IoU."""
    st = merge.stats
    arrays = (merge.class_probs, merge.scores, confidence, predicted_iou,
              st.predictive_variance, st.epistemic_variance, st.shannon_entropy,
              st.aleatoric_entropy, st.mutual_information, st.epistemic_total_variance,
              st.aleatoric_total_variance)
    try:  # a merge's own arrays have the kernel's types: taken as they are
        return _tables(*arrays, rows, bool(scale))
    except TypeError:  # another dtype or layout (no matching signature): converted
        return _tables(*(np.require(a, np.float64, "C") for a in arrays),
                       np.require(rows, np.int64, "C"), bool(scale))


@njit(types.Tuple((array_out(types.float64, 2), array_out(types.float64, 2),
                   array_out(types.float64, 2)))(F2, F1, F1, F1, F2, F2, F1, F1, F1, F1, F1, I1,
                                                 types.boolean), cache=True, nogil=True)
def _tables(probs, label_score, conf, iou, pred, epi, se, ae, mi, etv, atv, rows, scale):
    n, n_cls = probs.shape
    fg = np.empty((len(rows), n_cls - 1))
    cov = np.zeros((len(rows), 6))
    for k in range(len(rows)):
        i = rows[k]
        if i < 0 or i >= n:
            raise IndexError("published rows outside the merged detections")
        # numpy's where(isfinite(conf) & (p > 0), conf / p, 1.0), times every score
        f = conf[i] / label_score[i] if (scale and np.isfinite(conf[i])
                                         and label_score[i] > 0) else 1.0
        for c in range(1, n_cls):
            fg[k, c - 1] = probs[i, c] * f if scale else probs[i, c]
        for j in range(4):
            v = pred[i, _XYZYAW[j]]
            cov[k, _COV_AT[j]] = epi[i, _XYZYAW[j]] if np.isnan(v) else v
    figures = np.empty((n, 7))
    for i in range(n):
        figures[i, 0], figures[i, 1], figures[i, 2] = se[i], ae[i], mi[i]
        figures[i, 3], figures[i, 4], figures[i, 5], figures[i, 6] = etv[i], atv[i], conf[i], iou[i]
    return fg, cov, figures
