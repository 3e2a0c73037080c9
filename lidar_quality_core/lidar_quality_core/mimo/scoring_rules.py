"""Scoring rules and calibration errors of probabilistic detections (LiDAR-MIMO, paper IV.C;
Harakeh & Waslander 2021; authors' code mpitropov/uncertainty_eval ``scoring/``, ``ece.py``).

Everything is per detection and vectorized; the evaluation averages per partition
(TP / FP_ML / FP_BG, ``lidar_quality_core.detection_eval.fp_partition``).

Classification, over K + 1 classes (background included, a column of ``probs``):

* ``classification_nll`` = -log p[target], p floored at ``PROB_FLOOR`` (a 0 would be inf).
* ``brier_score`` = sum_k (p_k - onehot(target)_k)^2, in [0, 2] (the authors' sum, not a
  mean over classes).
* The evaluation's targets (authors' code): a TP its ground-truth class, every false
  positive (FP_ML and FP_BG) the background.
* ``marginal_calibration_error``: Kumar et al. 2019 (``uncertainty-calibration``'s
  ``get_calibration_error``, the authors' MCE): per class k, the l2 calibration error of
  p_k against [target == k] over ``n_bins`` (15) equal-mass bins, debiased (the binomial
  variance of each bin's label mean subtracted, clipped at 0); MCE = sqrt(mean_k CE_k^2).
  The library switches to per-value bins when the probabilities take few distinct values;
  here the bins are always equal-mass (ours: one estimator for all models).

Regression over the 7 box parameters x, y, z, l, w, h, yaw (predicted mean and variance,
independent dimensions):

* ``regression_nll`` = Gaussian NLL of x..h with the variances plus ``jitter`` (the authors
  add 1e-2 I to the covariance) + von Mises NLL of yaw with concentration 1 / var_yaw.
* ``energy_score`` = E||X - y|| - 1/2 E||X - X'|| (Gneiting et al. 2008), Monte Carlo with
  ``n_samples`` draws per detection, the second term over consecutive sample pairs (the
  authors', after probdet); Gaussian part (6-D, jitter as above) plus von Mises part for
  yaw. The yaw distance is wrapped to [0, pi] (ours: the authors' plain difference makes a
  yaw of pi - 0.01 against -pi + 0.01 an error of ~2 pi).
* ``regression_calibration_error``: Kuleshov et al. 2018. Per parameter the predicted CDF
  at the ground truth, F_i(y_i) (yaw: von Mises CDF of the wrapped difference); for levels
  p_j = j / 15, j = 1 .. 14 (the authors' levels; 0 and 1 are trivially calibrated) the
  squared gap between p_j and the fraction of F_i(y_i) < p_j, averaged over the levels,
  then over the 7 parameters.
"""
from __future__ import annotations

import numpy as np
from scipy.special import i0e, ndtr
from scipy.stats import vonmises

from lidar_quality_core.conventions import wrap_angle

__all__ = ["PROB_FLOOR", "YAW_VAR_FLOOR", "classification_nll", "brier_score",
           "marginal_calibration_error", "gaussian_nll", "von_mises_nll", "regression_nll",
           "energy_score", "sample_energy_score", "regression_cdf",
           "regression_calibration_error"]

PROB_FLOOR = 1e-12
#: Smallest yaw variance [rad^2]: a zero variance would be an infinite concentration.
YAW_VAR_FLOOR = 1e-8
LOG_2PI = float(np.log(2.0 * np.pi))


def _probs_target(probs, target):
    p = np.asarray(probs, np.float64)
    t = np.asarray(target).reshape(-1)
    if p.ndim != 2 or len(p) != len(t):
        raise ValueError(f"probs must be (n, K) with n = len(target); got {p.shape}, {t.shape}")
    if len(t) and (not np.issubdtype(t.dtype, np.integer) or t.min() < 0 or t.max() >= p.shape[1]):
        raise ValueError(f"targets must be integer columns in [0, {p.shape[1]})")
    return p, t.astype(np.intp)


# ------------------------------------------------------------------ classification
def classification_nll(probs, target) -> np.ndarray:
    """(n,) -log p[target] (natural log), p floored at ``PROB_FLOOR``."""
    p, t = _probs_target(probs, target)
    return -np.log(np.maximum(p[np.arange(len(t)), t], PROB_FLOOR))


def brier_score(probs, target) -> np.ndarray:
    """(n,) sum over the classes of (p_k - onehot(target)_k)^2."""
    p, t = _probs_target(probs, target)
    d = p.copy()
    d[np.arange(len(t)), t] -= 1.0
    return np.einsum("ij,ij->i", d, d)


def _equal_mass_bins(x: np.ndarray, n_bins: int) -> np.ndarray:
    """Bin index of each value: ``n_bins`` (at most n) near-equal parts of the sorted values,
    boundaries midway between neighbouring parts, equal boundaries merged (Kumar et al.)."""
    s = np.sort(x)
    k = min(n_bins, len(s))
    # np.array_split sizes: the first n % k parts one longer
    sizes = np.full(k, len(s) // k)
    sizes[:len(s) % k] += 1
    ends = np.cumsum(sizes)[:-1]  # first index of parts 1 .. k-1
    bounds = np.unique(np.r_[(s[ends - 1] + s[ends]) / 2.0, 1.0])
    # bisect_left: a value equal to a boundary belongs to the lower bin
    return np.searchsorted(bounds, x, side="left")


def _binary_sq_ce(p: np.ndarray, y: np.ndarray, n_bins: int, debias: bool) -> float:
    """Squared l2 calibration error of probabilities ``p`` for 0/1 labels ``y``."""
    b = _equal_mass_bins(p, n_bins)
    nb = np.bincount(b)
    has = nb > 0
    mp = np.bincount(b, weights=p)[has] / nb[has]
    my = np.bincount(b, weights=y)[has] / nb[has]
    n_b = nb[has].astype(np.float64)
    err = (mp - my) ** 2
    if debias:
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.where(n_b >= 2, err - my * (1.0 - my) / (n_b - 1.0), 0.0)
    return max(float(np.sum(n_b / len(p) * err)), 0.0)


def marginal_calibration_error(probs, target, *, n_bins: int = 15, debias: bool = True) -> float:
    """Kumar et al.'s marginal l2 calibration error over all K columns (module docstring);
    NaN for no detections."""
    p, t = _probs_target(probs, target)
    if not len(t):
        return float("nan")
    if p.min() < 0.0 or p.max() > 1.0:
        raise ValueError("probabilities must lie in [0, 1]")
    sq = [_binary_sq_ce(p[:, k], (t == k).astype(np.float64), n_bins, debias)
          for k in range(p.shape[1])]
    return float(np.sqrt(np.mean(sq)))


# ------------------------------------------------------------------ regression
def _box_arrays(mean, var, y=None):
    m = np.asarray(mean, np.float64).reshape(-1, 7)
    v = np.asarray(var, np.float64).reshape(-1, 7)
    if v.shape != m.shape:
        raise ValueError(f"variances {v.shape} do not match means {m.shape}")
    if y is None:
        return m, v
    g = np.asarray(y, np.float64).reshape(-1, 7)
    if g.shape != m.shape:
        raise ValueError(f"ground truth {g.shape} does not match means {m.shape}")
    return m, v, g


def gaussian_nll(mean, var, y) -> np.ndarray:
    """NLL of ``y`` under independent normals, summed over the last axis."""
    m, v, g = (np.asarray(a, np.float64) for a in (mean, var, y))
    return 0.5 * np.sum(LOG_2PI + np.log(v) + (g - m) ** 2 / v, axis=-1)


def _log_i0(kappa):
    return np.log(i0e(kappa)) + kappa  # i0e(k) = exp(-k) I0(k): no overflow


def von_mises_nll(mu, kappa, theta) -> np.ndarray:
    """NLL of angles ``theta`` under von Mises(mu, kappa): -kappa cos(theta - mu) + log(2 pi
    I0(kappa))."""
    k = np.asarray(kappa, np.float64)
    d = np.asarray(theta, np.float64) - np.asarray(mu, np.float64)
    return -k * np.cos(d) + LOG_2PI + _log_i0(k)


def _kappa(var_yaw):
    return 1.0 / np.maximum(np.asarray(var_yaw, np.float64), YAW_VAR_FLOOR)


def regression_nll(mean, var, y, *, jitter: float = 1e-2) -> np.ndarray:
    """(n,) Gaussian NLL of x, y, z, l, w, h (variances + ``jitter``) plus von Mises NLL of
    yaw (kappa = 1 / var_yaw)."""
    m, v, g = _box_arrays(mean, var, y)
    return (gaussian_nll(m[:, :6], v[:, :6] + jitter, g[:, :6])
            + von_mises_nll(m[:, 6], _kappa(v[:, 6]), g[:, 6]))


def sample_energy_score(samples, y, *, angular: bool = False) -> np.ndarray:
    """(n,) Monte Carlo energy score from ``samples`` (S, n, d) against ``y`` (n, d):
    mean_s ||x_s - y|| - 1/2 mean_s ||x_s - x_{s+1}||; ``angular``: differences wrapped
    to [-pi, pi) (one angle per row, d = 1)."""
    x = np.asarray(samples, np.float64)
    g = np.asarray(y, np.float64)
    if x.ndim != 3 or x.shape[1:] != g.shape:
        raise ValueError(f"samples must be (S, n, d) with y (n, d); got {x.shape}, {g.shape}")
    d1, d2 = x - g[None], x[:-1] - x[1:]
    if angular:
        d1, d2 = wrap_angle(d1), wrap_angle(d2)
    first = np.sqrt(np.einsum("snd,snd->sn", d1, d1)).mean(axis=0)
    second = (np.sqrt(np.einsum("snd,snd->sn", d2, d2)).mean(axis=0) if len(x) > 1
              else np.zeros(x.shape[1]))
    return first - 0.5 * second


def energy_score(mean, var, y, *, n_samples: int = 1000, jitter: float = 1e-2, seed: int = 0,
                 chunk: int = 256) -> np.ndarray:
    """(n,) energy score of the box distributions (module docstring): Gaussian x..h with
    variances + ``jitter``, plus von Mises yaw; ``n_samples`` seeded draws per box."""
    m, v, g = _box_arrays(mean, var, y)
    rng = np.random.default_rng(seed)
    out = np.empty(len(m))
    for a in range(0, len(m), chunk):
        sl = slice(a, a + chunk)
        mm, vv, gg = m[sl], v[sl], g[sl]
        z = rng.standard_normal((n_samples,) + mm[:, :6].shape)
        lin = mm[None, :, :6] + z * np.sqrt(vv[None, :, :6] + jitter)
        yaw = rng.vonmises(np.broadcast_to(mm[:, 6], (n_samples, len(mm))),
                           np.broadcast_to(_kappa(vv[:, 6]), (n_samples, len(mm))))
        out[sl] = (sample_energy_score(lin, gg[:, :6])
                   + sample_energy_score(yaw[..., None], gg[:, 6:7], angular=True))
    return out


def regression_cdf(mean, var, y) -> np.ndarray:
    """(n, 7) predicted CDF at the ground truth: normal CDF for x..h (no jitter), von Mises
    CDF of the wrapped yaw difference (in [0, 1], 0.5 at the mean)."""
    m, v, g = _box_arrays(mean, var, y)
    out = np.empty_like(m)
    with np.errstate(divide="ignore", invalid="ignore"):
        out[:, :6] = ndtr((g[:, :6] - m[:, :6]) / np.sqrt(v[:, :6]))
    out[:, 6] = vonmises.cdf(wrap_angle(g[:, 6] - m[:, 6]), _kappa(v[:, 6]))
    return out


def regression_calibration_error(mean, var, y, *, n_levels: int = 15) -> dict:
    """Kuleshov calibration error (module docstring): ``{"per_parameter": (7,), "mean",
    "max"}``; NaN without detections."""
    cdf = regression_cdf(mean, var, y)
    if not len(cdf):
        nan = float("nan")
        return {"per_parameter": np.full(7, nan), "mean": nan, "max": nan}
    levels = np.arange(1, n_levels) / n_levels
    frac = (cdf[None, :, :] < levels[:, None, None]).mean(axis=1)   # (levels, 7)
    per = ((frac - levels[:, None]) ** 2).mean(axis=0)
    return {"per_parameter": per, "mean": float(per.mean()), "max": float(per.max())}
