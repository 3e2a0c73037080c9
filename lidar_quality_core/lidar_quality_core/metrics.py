"""Metrics of the meta tasks (own numpy implementations, cross-checked against sklearn).

Conventions:

* Arguments are always ``(y_true, prediction)``, in that order. ``y_true`` of the binary
  metrics must contain only 0/1 (bool, int or float); anything else raises ValueError,
  which also catches most swapped calls with continuous scores.
* Non-finite inputs (NaN, inf) and length mismatches raise ValueError.
* Undefined values return ``nan`` without raising or warning: AUROC / AUPRC when only one
  class is present (AUPRC with only positives is trivially 1 but carries no
  information, so it is ``nan`` too), R^2 when ``y_true`` is constant or ``n < 2``, and
  every metric of an empty input.
* Calibration is of the positive-class probability: in each bin the mean ``prob`` is
  compared with the fraction of positives. Bins are ``n_bins`` equal-width bins over
  [0, 1], left-closed ``[e_k, e_{k+1})``, the last one closed ``[e_{n-1}, 1]`` so that
  ``prob == 1.0`` falls in the last bin. Probabilities outside [0, 1] raise ValueError.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import rankdata

__all__ = [
    "accuracy",
    "auroc",
    "auprc",
    "r2",
    "mae",
    "ece",
    "mce",
    "brier",
    "ReliabilityDiagram",
    "reliability_diagram",
    "summary",
    "confusion_matrix",
    "per_class_iou",
    "mean_iou",
]


def _vec(x: Any, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        raise ValueError(f"{name} must be 1-D, got a scalar")
    a = a.reshape(-1) if a.ndim == 2 and 1 in a.shape else a
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def _pair(y_true: Any, y_other: Any, other_name: str) -> tuple[np.ndarray, np.ndarray]:
    y = _vec(y_true, "y_true")
    o = _vec(y_other, other_name)
    if y.shape != o.shape:
        raise ValueError(f"length mismatch: y_true has {y.size}, {other_name} has {o.size}")
    return y, o


def _binary(y: np.ndarray) -> np.ndarray:
    if not np.all((y == 0) | (y == 1)):
        bad = np.unique(y[(y != 0) & (y != 1)])[:5]
        raise ValueError(f"y_true must be binary 0/1, found values like {bad.tolist()}")
    return y.astype(bool)


def _prob(p: np.ndarray, name: str = "prob") -> np.ndarray:
    if p.size and (p.min() < 0.0 or p.max() > 1.0):
        raise ValueError(f"{name} must lie in [0, 1], got range [{p.min()}, {p.max()}]")
    return p


def accuracy(y_true: Any, y_pred_or_prob: Any, threshold: float = 0.5) -> float:
    """Fraction correct; a prediction counts as positive iff ``value >= threshold``.

    Hard 0/1 predictions work unchanged (for any ``0 < threshold <= 1``).
    """
    y, p = _pair(y_true, y_pred_or_prob, "y_pred_or_prob")
    y = _binary(y)
    if y.size == 0:
        return float("nan")
    return float(np.mean((p >= threshold) == y))


def auroc(y_true: Any, score: Any) -> float:
    """Area under the ROC curve (Mann-Whitney U with average ranks for ties)."""
    y, s = _pair(y_true, score, "score")
    y = _binary(y)
    n_pos = int(y.sum())
    n_neg = y.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(s)  # "average" ties -> a tie between classes counts one half
    u = ranks[y].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def auprc(y_true: Any, score: Any) -> float:
    """Average precision ``sum_k (R_k - R_{k-1}) P_k`` over distinct score thresholds.

    Step-wise (no interpolation), ties in score form one threshold; equals sklearn's
    ``average_precision_score``.
    """
    y, s = _pair(y_true, score, "score")
    y = _binary(y)
    n_pos = int(y.sum())
    if n_pos == 0 or n_pos == y.size:
        return float("nan")
    order = np.argsort(-s, kind="stable")
    s_sorted = s[order]
    tp = np.cumsum(y[order])
    # Last index of each run of equal scores = one threshold.
    last = np.r_[np.nonzero(np.diff(s_sorted))[0], s.size - 1]
    tp = tp[last]
    precision = tp / (last + 1.0)
    recall = tp / n_pos
    return float(np.sum(np.diff(recall, prepend=0.0) * precision))


def r2(y_true: Any, y_pred: Any) -> float:
    """Coefficient of determination ``1 - SS_res / SS_tot``; nan if ``SS_tot == 0``."""
    y, p = _pair(y_true, y_pred, "y_pred")
    if y.size < 2:
        return float("nan")
    ss_tot = np.sum((y - y.mean()) ** 2)
    if ss_tot == 0.0:
        return float("nan")
    return float(1.0 - np.sum((y - p) ** 2) / ss_tot)


def mae(y_true: Any, y_pred: Any) -> float:
    """Mean absolute error; nan for empty input."""
    y, p = _pair(y_true, y_pred, "y_pred")
    return float(np.mean(np.abs(y - p))) if y.size else float("nan")


def brier(y_true: Any, prob: Any) -> float:
    """Brier score ``mean((prob - y)^2)``; nan for empty input."""
    y, p = _pair(y_true, prob, "prob")
    y = _binary(y)
    _prob(p)
    return float(np.mean((p - y) ** 2)) if y.size else float("nan")


@dataclass(frozen=True)
class ReliabilityDiagram:
    """Per-bin calibration data; ``mean_confidence`` / ``accuracy`` are nan in empty bins.

    ``edges`` has ``n_bins + 1`` entries; ``accuracy`` is the fraction of positives.
    """

    edges: np.ndarray
    counts: np.ndarray
    mean_confidence: np.ndarray
    accuracy: np.ndarray

    @property
    def nonempty(self) -> np.ndarray:
        return self.counts > 0

    @property
    def gaps(self) -> np.ndarray:
        """``|accuracy - mean_confidence|`` per bin (nan where empty)."""
        return np.abs(self.accuracy - self.mean_confidence)

    @property
    def ece(self) -> float:
        n = self.counts.sum()
        if n == 0:
            return float("nan")
        ne = self.nonempty
        return float(np.sum(self.counts[ne] / n * self.gaps[ne]))

    @property
    def mce(self) -> float:
        ne = self.nonempty
        return float(self.gaps[ne].max()) if ne.any() else float("nan")


def reliability_diagram(y_true: Any, prob: Any, n_bins: int = 10) -> ReliabilityDiagram:
    """Bin ``prob`` into ``n_bins`` equal-width bins over [0, 1] (see module doc)."""
    if int(n_bins) != n_bins or n_bins < 1:
        raise ValueError(f"n_bins must be a positive integer, got {n_bins}")
    n_bins = int(n_bins)
    y, p = _pair(y_true, prob, "prob")
    y = _binary(y)
    _prob(p)
    # k / n_bins (not linspace) so that edges are the doubles of the literals: 0.3 is
    # the edge 0.3 and lands in [0.3, 0.4). The reported edges are the ones used.
    edges = np.arange(n_bins + 1) / n_bins
    idx = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, n_bins - 1)
    counts = np.bincount(idx, minlength=n_bins)
    sum_p = np.bincount(idx, weights=p, minlength=n_bins)
    sum_y = np.bincount(idx, weights=y.astype(np.float64), minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        conf = np.where(counts > 0, sum_p / counts, np.nan)
        acc = np.where(counts > 0, sum_y / counts, np.nan)
    return ReliabilityDiagram(edges, counts, conf, acc)


def ece(y_true: Any, prob: Any, n_bins: int = 10) -> float:
    """Expected calibration error ``sum_b (n_b / n) |acc_b - conf_b|``; nan if empty."""
    return reliability_diagram(y_true, prob, n_bins).ece


def mce(y_true: Any, prob: Any, n_bins: int = 10) -> float:
    """Maximum calibration error over non-empty bins; nan if empty."""
    return reliability_diagram(y_true, prob, n_bins).mce


def summary(
    y_true_binary: Any,
    conf: Any,
    iou_true: Any = None,
    iou_pred: Any = None,
    *,
    threshold: float = 0.5,
    n_bins: int = 10,
) -> dict[str, float]:
    """All classification metrics of ``conf``, plus IoU regression metrics if given.

    Keys: n, positive_rate, accuracy, auroc, auprc, brier, ece, mce and, with both IoU
    arrays, iou_r2, iou_mae, iou_n.
    """
    y, p = _pair(y_true_binary, conf, "conf")
    yb = _binary(y)
    rd = reliability_diagram(y, p, n_bins)
    out = {
        "n": float(y.size),
        "positive_rate": float(yb.mean()) if y.size else float("nan"),
        "accuracy": accuracy(y, p, threshold),
        "auroc": auroc(y, p),
        "auprc": auprc(y, p),
        "brier": brier(y, p),
        "ece": rd.ece,
        "mce": rd.mce,
    }
    if (iou_true is None) != (iou_pred is None):
        raise ValueError("give both iou_true and iou_pred or neither")
    if iou_true is not None:
        it, ip = _pair(iou_true, iou_pred, "iou_pred")
        out.update(iou_n=float(it.size), iou_r2=r2(it, ip), iou_mae=mae(it, ip))
    return out


# -- semantic segmentation ---------------------------------------------------------------
# Confusion matrices are indexed [true class, predicted class]. Points whose true class is
# ``ignore`` (SemanticKITTI: unlabeled) are left out entirely; a prediction of the ignored
# class on a labelled point still counts as an error (a false negative of the true class).


def _labels(y: Any, name: str, n_classes: int) -> np.ndarray:
    a = np.asarray(y)
    if a.ndim != 1:
        a = a.reshape(-1)
    if a.size and not np.issubdtype(a.dtype, np.integer):
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise ValueError(f"{name} must hold integer class ids")
    a = a.astype(np.int64)
    if a.size and (a.min() < 0 or a.max() >= n_classes):
        raise ValueError(f"{name} has class ids outside [0, {n_classes}): "
                         f"[{a.min()}, {a.max()}]")
    return a


def confusion_matrix(y_true: Any, y_pred: Any, n_classes: int,
                     ignore: int | None = None) -> np.ndarray:
    """(n_classes, n_classes) int64 counts ``cm[true, pred]``; rows of ``ignore`` are 0."""
    n_classes = int(n_classes)
    if n_classes < 1:
        raise ValueError(f"n_classes must be >= 1, got {n_classes}")
    t = _labels(y_true, "y_true", n_classes)
    p = _labels(y_pred, "y_pred", n_classes)
    if t.shape != p.shape:
        raise ValueError(f"length mismatch: y_true has {t.size}, y_pred has {p.size}")
    if ignore is not None:
        keep = t != ignore
        t, p = t[keep], p[keep]
    return np.bincount(t * n_classes + p, minlength=n_classes * n_classes).reshape(
        n_classes, n_classes).astype(np.int64)


def per_class_iou(cm: Any) -> np.ndarray:
    """IoU ``TP / (TP + FP + FN)`` per class from a confusion matrix; nan where a class is
    neither in the ground truth nor predicted (union 0)."""
    cm = np.asarray(cm, dtype=np.float64)
    if cm.ndim != 2 or cm.shape[0] != cm.shape[1]:
        raise ValueError(f"confusion matrix must be square, got shape {cm.shape}")
    tp = np.diag(cm)
    union = cm.sum(axis=0) + cm.sum(axis=1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, tp / union, np.nan)


def mean_iou(cm: Any, ignore: int | None = None) -> float:
    """Mean IoU over the classes present in the ground truth (row sum > 0), ``ignore``
    excluded (SemanticKITTI convention). A class that is only predicted, never true, is
    left out of the mean (its false positives still lower the IoU of the true classes
    they were taken from). nan if no class is present."""
    cm = np.asarray(cm, dtype=np.float64)
    iou = per_class_iou(cm)
    present = cm.sum(axis=1) > 0
    if ignore is not None:
        present[int(ignore)] = False
    return float(iou[present].mean()) if present.any() else float("nan")
