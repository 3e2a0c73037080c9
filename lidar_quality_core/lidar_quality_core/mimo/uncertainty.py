"""LiDAR-MIMO uncertainty statistics of clusters of detections (paper sections II.B, IV.C).

Members of a cluster are the detections of one object by the K heads. Everything here is
vectorized over all clusters of a frame: the members are given grouped, cluster after
cluster (``starts`` = offset of each cluster's first member), and ``top`` names each
cluster's highest-confidence member.

Definitions (method-details.md, LiDAR-MIMO; authors' code mpitropov/uncertainty_eval):

* Classification, base 2, ``p_m`` = member m's class distribution (background included):
  SE = H(mean_m p_m) (Shannon entropy of the mean distribution, total uncertainty),
  AE = mean_m H(p_m) (aleatoric entropy), MI = SE - AE (epistemic; >= 0 by concavity,
  rounding clipped at 0). 0 log 0 = 0. Note: SE is of the *mean of the member
  distributions*, not of the merged distribution softmax(mean logits) that labels the
  merged box (the authors' code does the same; only this way MI >= 0).
* Regression over the 7 parameters x, y, z, l, w, h, yaw: epistemic variance = the
  population variance (divide by the member count) of the member values; ETV = its sum
  (trace of the members' covariance, paper IV.C). Computed as E[d^2] - E[d]^2 of the
  deviations d from the top member: shift-invariant, no cancellation at ~100 m
  coordinates, exact 0 for equal members. Aleatoric variance = the mean of the
  members' predicted variances; ATV = its sum. Predictive variance = epistemic +
  aleatoric per parameter, except yaw (below). Unknown predicted variances (NaN) make
  the aleatoric and predictive figures NaN, never the epistemic ones.
* Yaw. The authors take the variance of the raw yaw values (``yaw_deviation="raw"``), so
  members at +pi - 0.01 and -pi + 0.01 (0.02 rad apart) add ~pi^2 to ETV. Ours,
  default ``"wrapped"``: the deviations from the top member's yaw are wrapped to
  [-pi, pi) before taking the variance (those two members: 1e-4). A heading flip of pi
  stays a large disagreement (pi^2/4 for two members): it is one. Predictive yaw
  variance: the top member's predicted variance, since the merged yaw is the top
  member's (authors' code, ``yaw_variance="top"``); ``"mixture"`` uses epistemic (wrapped
  or raw as above) + aleatoric like the other parameters.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from lidar_quality_core.conventions import wrap_angle
from lidar_quality_core.kernel_types import F2 as _F2, I1 as _I1, array_out
from numba import njit, types
from scipy.special import entr

__all__ = ["BOX_PARAMS", "ClusterStatistics", "entropy_bits", "wrap_angle", "group_mean",
           "classification_statistics", "regression_statistics", "cluster_statistics",
           "group_statistics", "GROUP_STATISTICS"]

BOX_PARAMS = ("x", "y", "z", "l", "w", "h", "yaw")
YAW_DEVIATIONS = ("wrapped", "raw")
YAW_VARIANCES = ("top", "mixture")
LN2 = float(np.log(2.0))


def entropy_bits(p: np.ndarray) -> np.ndarray:
    """Shannon entropy in bits along the last axis (0 log 0 = 0)."""
    p = np.asarray(p, np.float64)
    return entr(p) @ np.full(p.shape[-1], 1.0 / LN2)  # matmul: a fast row sum


def group_mean(x: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Mean over each group of rows ``x[starts[g] : starts[g] + counts[g]]``."""
    s = np.add.reduceat(x, starts, axis=0)
    return s / (counts[:, None] if s.ndim == 2 else counts)


@dataclass
class ClusterStatistics:
    """Per-cluster statistics, arrays of length C (``(C, 7)`` for the per-parameter ones)."""

    cluster_size: np.ndarray               # members (may exceed K: DBSCAN semantics)
    shannon_entropy: np.ndarray            # SE [bit]
    aleatoric_entropy: np.ndarray          # AE [bit]
    mutual_information: np.ndarray         # MI = SE - AE [bit]
    epistemic_total_variance: np.ndarray   # ETV
    aleatoric_total_variance: np.ndarray   # ATV (NaN if a member's variances are unknown)
    epistemic_variance: np.ndarray         # (C, 7) between-member variance per parameter
    aleatoric_variance: np.ndarray         # (C, 7) mean predicted variance per parameter
    predictive_variance: np.ndarray        # (C, 7) epistemic + aleatoric (yaw: see module doc)

    @classmethod
    def empty(cls) -> "ClusterStatistics":
        z, z7 = np.zeros(0), np.zeros((0, 7))
        return cls(np.zeros(0, np.int64), z, z.copy(), z.copy(), z.copy(), z.copy(), z7,
                   z7.copy(), z7.copy())


def classification_statistics(probs: np.ndarray, starts: np.ndarray, counts: np.ndarray):
    """``(SE, AE, MI)`` in bits of grouped member distributions ``probs`` (M, C)."""
    se = entropy_bits(group_mean(probs, starts, counts))
    ae = group_mean(entropy_bits(probs), starts, counts)
    return se, ae, np.maximum(se - ae, 0.0)


def _check(yaw_deviation, yaw_variance):
    if yaw_deviation not in YAW_DEVIATIONS:
        raise ValueError(f"yaw_deviation must be one of {YAW_DEVIATIONS}, got {yaw_deviation!r}")
    if yaw_variance not in YAW_VARIANCES:
        raise ValueError(f"yaw_variance must be one of {YAW_VARIANCES}, got {yaw_variance!r}")


def _deviations(boxes, top, counts, yaw_deviation):
    # Deviations from the group's top member: the variance is shift-invariant, equal
    # members give exact zeros, and the wrapped yaw needs a reference inside the group.
    dev = boxes - np.repeat(boxes[top], counts, axis=0)
    if yaw_deviation == "wrapped":
        dev[:, 6] = wrap_angle(dev[:, 6])
    return dev


def regression_statistics(boxes: np.ndarray, variances: np.ndarray, starts: np.ndarray,
                          counts: np.ndarray, top: np.ndarray, *,
                          yaw_deviation: str = "wrapped", yaw_variance: str = "top"):
    """``(epistemic (C,7), aleatoric (C,7), predictive (C,7))`` of grouped member boxes
    (M, 7) with predicted variances (M, 7) (NaN: unknown); ``top`` = member row of each
    group's top member."""
    _check(yaw_deviation, yaw_variance)
    dev = _deviations(boxes, top, counts, yaw_deviation)
    m = group_mean(np.concatenate([dev, dev * dev, variances], axis=1), starts, counts)
    return _regression(m, variances, top, yaw_variance)


def _regression(m, variances, top, yaw_variance):
    """From the group means of [dev, dev^2, variances] (C, 21)."""
    epistemic = np.maximum(m[:, 7:14] - m[:, :7] ** 2, 0.0)
    aleatoric = m[:, 14:21]
    predictive = epistemic + aleatoric
    if yaw_variance == "top":
        predictive[:, 6] = variances[top, 6]
    return epistemic, aleatoric, predictive


@njit(inline="always")
def _entropy_bits_row(p, r, inv_ln2):
    # entropy_bits of row r: scipy's entr (-x log x, 0 at 0, -inf below 0, NaN kept)
    h = 0.0
    for c in range(p.shape[1]):
        x = p[r, c]
        h += (-x * np.log(x) if x > 0.0 else 0.0 if x == 0.0 else -np.inf if x < 0.0
              else x) * inv_ln2
    return h


#: numba type of :func:`group_statistics`' result (for kernels that return it)
GROUP_STATISTICS = types.Tuple((array_out(types.int64),) + (array_out(types.float64),) * 5
                               + (array_out(types.float64, 2),) * 3)


@njit(GROUP_STATISTICS(_F2, _F2, _F2, _I1, _I1, types.boolean, types.boolean),
      cache=True, nogil=True)
def group_statistics(probs, boxes, variances, starts, top, wrapped, top_yaw):
    """:func:`cluster_statistics` in one compiled pass over the grouped members:
    ``(counts, SE, AE, MI, ETV, ATV, epistemic, aleatoric, predictive)``. ``wrapped``:
    ``yaw_deviation == "wrapped"``; ``top_yaw``: ``yaw_variance == "top"``. Each group's
    sums run member after member, as numpy's grouped sums (reduceat) did: a frame's
    ~50 clusters cost some 50 numpy calls there, each far dearer than its arithmetic."""
    n_groups, n_rows, n_cls = starts.shape[0], boxes.shape[0], probs.shape[1]
    inv_ln2 = 1.0 / np.log(2.0)
    counts = np.empty(n_groups, np.int64)
    se, ae, mi = np.empty(n_groups), np.empty(n_groups), np.empty(n_groups)
    etv, atv = np.empty(n_groups), np.empty(n_groups)
    epi, ale, pred = np.empty((n_groups, 7)), np.empty((n_groups, 7)), np.empty((n_groups, 7))
    m1, m2, mp = np.empty(7), np.empty(7), np.empty((1, n_cls))
    for g in range(n_groups):
        a = starts[g]
        b = starts[g + 1] if g + 1 < n_groups else n_rows
        t = top[g]
        counts[g] = b - a
        m1[:] = 0.0
        m2[:] = 0.0
        ale[g] = 0.0
        mp[:] = 0.0
        h = 0.0
        for r in range(a, b):
            for k in range(7):
                d = boxes[r, k] - boxes[t, k]
                if k == 6 and wrapped:   # wrap_angle: (d + pi) mod 2 pi - pi
                    d = (d + np.pi) % (2.0 * np.pi) - np.pi
                m1[k] += d
                m2[k] += d * d
                ale[g, k] += variances[r, k]
            h += _entropy_bits_row(probs, r, inv_ln2)
            for c in range(n_cls):
                mp[0, c] += probs[r, c]
        n = np.float64(b - a)
        e_sum, a_sum = 0.0, 0.0
        for k in range(7):
            v = m2[k] / n - (m1[k] / n) ** 2
            epi[g, k] = 0.0 if v < 0.0 else v   # NaN stays NaN (np.maximum)
            ale[g, k] /= n
            pred[g, k] = epi[g, k] + ale[g, k]
            e_sum += epi[g, k]
            a_sum += ale[g, k]
        if top_yaw:
            pred[g, 6] = variances[t, 6]
        etv[g], atv[g] = e_sum, a_sum
        for c in range(n_cls):
            mp[0, c] /= n
        se[g] = _entropy_bits_row(mp, 0, inv_ln2)
        ae[g] = h / n
        v = se[g] - ae[g]
        mi[g] = 0.0 if v < 0.0 else v
    return counts, se, ae, mi, etv, atv, epi, ale, pred


def cluster_statistics(probs: np.ndarray, boxes: np.ndarray, variances: np.ndarray,
                       starts: np.ndarray, top: np.ndarray, *, yaw_deviation: str = "wrapped",
                       yaw_variance: str = "top") -> ClusterStatistics:
    """All statistics of clusters whose members are rows ``starts[g]`` .. of the grouped
    ``probs`` (M, C), ``boxes`` (M, 7) and ``variances`` (M, 7) (one compiled pass:
    :func:`group_statistics`; :func:`classification_statistics` and
    :func:`regression_statistics` are the same definitions in numpy)."""
    _check(yaw_deviation, yaw_variance)
    starts = np.asarray(starts, np.int64)
    if len(starts) == 0:
        return ClusterStatistics.empty()
    f = np.float64
    return ClusterStatistics(*group_statistics(
        np.require(probs, f, "C"), np.require(boxes, f, "C"), np.require(variances, f, "C"),
        starts, np.asarray(top, np.int64), yaw_deviation == "wrapped", yaw_variance == "top"))
