"""Recalibration of detections for the LiDAR-MIMO evaluation (paper IV.D, after Harakeh &
Waslander and Feng et al.): fitted on a recalibration set, applied to an evaluation set.

The authors' sequence (``run_uncertainty_eval.sh``: score thresholds, temperatures on the
thresholded detections, thresholds again on the scaled scores), per class c:

1. Score threshold: the one that maximizes F1 = 2 P R / (P + R) of the class's detections
   with score >= threshold (operating points at the distinct scores,
   ``detection_eval.precision_recall``; ties go to the highest threshold). A class without
   ground truth or without detections keeps every detection (threshold 0).
2. Temperature scaling (Guo et al. 2017): the class distribution p of a detection labelled
   c becomes softmax(log p / T_c), T_c minimizing the mean NLL of the scoring-rule targets
   (K + 1 classes) of the class-c detections that pass step 1. The NLL is convex in 1 / T,
   so a bounded scalar search on 1 / T in [1 / ``T_MAX``, 1 / ``T_MIN``] finds the optimum.
   Fewer than ``MIN_FIT`` detections, or targets of one class only: T = 1.
3. The F1-optimal threshold again, on the scaled scores (the scaled probability of the
   label). Applying: scale, then keep the detections whose scaled score passes it.

A detection's label is a class column (1..C, column 0 = background) given by the caller:
scaling keeps the order of the columns, but the label need not be the arg max (the meta
model's distributions put the confidence on the merged label).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import minimize_scalar

from lidar_quality_core.detection_eval import precision_recall

from .scoring_rules import PROB_FLOOR

__all__ = ["T_MIN", "T_MAX", "MIN_FIT", "f1_optimal_threshold", "apply_temperature",
           "fit_temperature", "Recalibration"]

T_MIN, T_MAX = 0.05, 20.0
MIN_FIT = 10


def f1_optimal_threshold(scores, tp, n_gt: int) -> tuple[float, float]:
    """``(threshold, F1)``: the score threshold (accept score >= threshold) of maximal F1
    over the detections ``scores`` with TP flags ``tp`` and ``n_gt`` ground-truth boxes;
    ``(0.0, nan)`` when there is nothing to fit."""
    s = np.asarray(scores, np.float64).reshape(-1)
    if not len(s) or not n_gt:
        return 0.0, float("nan")
    precision, recall, thr = precision_recall(s, tp, n_gt)
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(precision + recall > 0, 2 * precision * recall / (precision + recall), 0.0)
    k = int(np.argmax(f1))  # first maximum = highest threshold (descending operating points)
    return float(thr[k]), float(f1[k])


def _logits(probs) -> np.ndarray:
    return np.log(np.maximum(np.asarray(probs, np.float64), PROB_FLOOR))


def _softmax(z: np.ndarray) -> np.ndarray:
    z = z - z.max(axis=1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=1, keepdims=True)


def apply_temperature(probs, temperature) -> np.ndarray:
    """softmax(log p / T) row-wise; ``temperature`` a scalar or one value per row. Rows
    with T = 1 are returned as they are (the log floor would turn 0 into 1e-12)."""
    p = np.asarray(probs, np.float64)
    t = np.broadcast_to(np.asarray(temperature, np.float64).reshape(-1), (len(p),))
    return np.where((t == 1.0)[:, None], p, _softmax(_logits(p) / t[:, None]))


def _mean_nll(z: np.ndarray, target: np.ndarray, beta: float) -> float:
    zz = z * beta
    zz -= zz.max(axis=1, keepdims=True)
    lse = np.log(np.exp(zz).sum(axis=1))
    return float(np.mean(lse - zz[np.arange(len(target)), target]))


def fit_temperature(probs, target) -> float:
    """T minimizing the mean NLL of ``target`` under softmax(log ``probs`` / T), in
    [``T_MIN``, ``T_MAX``]; 1.0 with fewer than ``MIN_FIT`` rows or a single target class."""
    z = _logits(probs)
    t = np.asarray(target, np.intp).reshape(-1)
    if z.ndim != 2 or len(z) != len(t):
        raise ValueError(f"probs must be (n, K) with n = len(target); got {z.shape}, {t.shape}")
    if len(t) < MIN_FIT or np.unique(t).size < 2:
        return 1.0
    res = minimize_scalar(lambda b: _mean_nll(z, t, b), bounds=(1.0 / T_MAX, 1.0 / T_MIN),
                          method="bounded", options={"xatol": 1e-6})
    return float(1.0 / res.x)


def _label_scores(probs, label_cols) -> np.ndarray:
    p = np.asarray(probs, np.float64)
    return p[np.arange(len(p)), np.asarray(label_cols, np.intp)] if len(p) else np.zeros(0)


@dataclass
class Recalibration:
    """Per-class score thresholds (on the scaled scores) and temperatures (module
    docstring); classes are named, detections carry their label column."""

    class_names: tuple = ()
    thresholds: dict = field(default_factory=dict)       # class -> threshold (scaled score)
    temperatures: dict = field(default_factory=dict)     # class -> T
    raw_thresholds: dict = field(default_factory=dict)   # class -> step 1 threshold
    f1: dict = field(default_factory=dict)               # class -> F1 at ``thresholds``

    @classmethod
    def fit(cls, class_names: Sequence[str], label_cols, tp, n_gt: dict, probs,
            target) -> "Recalibration":
        """Fit on recalibration detections: ``label_cols`` (1..C), ``tp`` (bool), ``n_gt``
        {class: ground-truth boxes}, ``probs`` (n, 1 + C) and their scoring-rule ``target``
        columns. Ignored detections must be left out."""
        lab = np.asarray(label_cols, np.intp).reshape(-1)
        tp = np.asarray(tp, bool).reshape(-1)
        probs = np.asarray(probs, np.float64)
        target = np.asarray(target, np.intp).reshape(-1)
        scores = _label_scores(probs, lab)
        out = cls(tuple(class_names))
        for k, c in enumerate(class_names):
            sel = lab == k + 1
            g = int(n_gt.get(c, 0))
            thr, _ = f1_optimal_threshold(scores[sel], tp[sel], g)
            keep = sel & (scores >= thr)
            t = fit_temperature(probs[keep], target[keep])
            scaled = _label_scores(apply_temperature(probs[sel], t), lab[sel])
            out.raw_thresholds[c], out.temperatures[c] = thr, t
            out.thresholds[c], out.f1[c] = f1_optimal_threshold(scaled, tp[sel], g)
        return out

    def _per_row(self, table: dict, label_cols, default: float) -> np.ndarray:
        lab = np.asarray(label_cols, np.intp).reshape(-1)
        vals = np.array([table.get(c, default) for c in self.class_names] or [default])
        return vals[lab - 1] if len(self.class_names) else np.full(len(lab), default)

    def calibrate(self, label_cols, probs) -> np.ndarray:
        """Class distributions scaled with the temperature of each row's class."""
        p = np.asarray(probs, np.float64)
        if not len(p):
            return p.copy()
        return apply_temperature(p, self._per_row(self.temperatures, label_cols, 1.0))

    def keep(self, label_cols, scaled_probs) -> np.ndarray:
        """(n,) bool: the scaled score of the label passes its class's threshold."""
        return (_label_scores(scaled_probs, label_cols)
                >= self._per_row(self.thresholds, label_cols, 0.0))

    def apply(self, label_cols, probs) -> tuple[np.ndarray, np.ndarray]:
        """``(kept (n,) bool, scaled distributions of the kept rows)``."""
        cal = self.calibrate(label_cols, probs)
        keep = self.keep(label_cols, cal)
        return keep, cal[keep]

    def as_dict(self) -> dict:
        return {"thresholds": dict(self.thresholds), "temperatures": dict(self.temperatures),
                "raw_thresholds": dict(self.raw_thresholds), "f1": dict(self.f1)}
