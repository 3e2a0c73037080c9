"""LiDAR-MIMO merging figures (``lidar_quality_core.mimo.merging.merge_heads``, one thread).

Frames: 100 boxes per head, K heads; 90 objects at least 5 m apart in a 5-60 m annulus
(cars, pedestrians, cyclists), 70 seen by every head, 20 "hard" ones seen by each head
with probability 0.5, plus single-head false positives anywhere (also on objects) up to
100 boxes per head. Per head: centre jitter
0.05 m + 0.4 % of the range, 3 % size jitter, 0.03 rad yaw jitter, 3 % heading flips by
pi; log-probability logits over 5 columns (0 background) and predicted variances, like
the reference multi-head detector. Each repetition merges the next of 20 frames.

Figures (ms, p50 / p99 over the repetitions):
* ``mimo.merge_ms``: K = 4 x 100 boxes (the larger case; goal p99 <= 2 ms);
* ``mimo.merge_k2_ms``: K = 2 x 100 boxes (goal p99 <= 2 ms);
* ``mimo.dbscan_{own,sklearn}_k{2,4}_ms`` (medians): the clustering step alone on the
  frames' neighbour pairs, our DBSCAN vs scikit-learn's on a dense precomputed matrix
  (the choice documented in lidar_quality_core.mimo.clustering); ``mimo.pairs_k{2,4}_ms``:
  the pairwise IoU step.
"""
from __future__ import annotations

import itertools

import numpy as np

N_FRAMES = 20
PER_HEAD = 100
N_EASY, N_HARD = 70, 20
_SIZE = np.array([[4.5, 1.85, 1.6], [0.8, 0.7, 1.75], [1.8, 0.7, 1.7]])
_CLASS_P = np.array([0.7, 0.15, 0.15])
_CLASS_COL = np.array([1, 3, 4])  # columns of car, pedestrian, cyclist (0 background)


def _annulus(rng, n):
    r = np.sqrt(rng.uniform(5.0**2, 60.0**2, n))
    a = rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([r * np.cos(a), r * np.sin(a)])


def _place(rng, n, spacing=5.0):
    """Object centres at least ``spacing`` apart."""
    out = np.zeros((0, 2))
    while len(out) < n:
        p = _annulus(rng, 1)
        if not len(out) or np.min(np.hypot(*(out - p).T)) >= spacing:
            out = np.vstack([out, p])
    return out


def _logits(rng, cols, strength):
    z = rng.normal(0.0, 1.0, (len(cols), 5))
    z[np.arange(len(cols)), cols] += strength
    return z - np.log(np.exp(z).sum(axis=1, keepdims=True))  # log-probabilities


def synthetic_heads(K: int, seed: int = 0):
    """One frame: a list of K ``(boxes, logits, variances)``."""
    rng = np.random.default_rng([seed, K])
    n_obj = N_EASY + N_HARD
    # objects spaced apart, then false positives anywhere (also on or beside objects)
    xy = np.vstack([_place(rng, n_obj), _annulus(rng, K * PER_HEAD)])
    cls = rng.choice(3, n_obj + K * PER_HEAD, p=_CLASS_P)
    size = _SIZE[cls] * rng.normal(1.0, 0.05, (len(cls), 3))
    base = np.column_stack([xy, np.full(len(cls), -1.0), size,
                            rng.uniform(-np.pi, np.pi, len(cls))])
    seen = np.ones((K, n_obj), bool)
    seen[:, N_EASY:] = rng.random((K, N_HARD)) < 0.5
    heads, fp_next = [], n_obj
    for k in range(K):
        idx = np.flatnonzero(seen[k])
        n_fp = PER_HEAD - len(idx)
        idx = np.concatenate([idx, np.arange(fp_next, fp_next + n_fp)])
        fp_next += n_fp
        b = base[idx].copy()
        dist = np.hypot(b[:, 0], b[:, 1])
        b[:, :2] += rng.normal(0.0, 1.0, (len(b), 2)) * (0.05 + 0.004 * dist)[:, None]
        b[:, 3:6] *= rng.normal(1.0, 0.03, (len(b), 3))
        b[:, 6] += rng.normal(0.0, 0.03, len(b)) + np.pi * (rng.random(len(b)) < 0.03)
        b[:, 6] = (b[:, 6] + np.pi) % (2 * np.pi) - np.pi
        strength = np.where(idx < n_obj, 3.0, 0.5)
        lg = _logits(rng, _CLASS_COL[cls[idx]], strength)
        sd = (0.05 + 0.005 * dist)[:, None] * np.array([1, 1, 0.5, 0.5, 0.3, 0.3, 0.2])
        heads.append((b, lg, (sd * rng.uniform(0.7, 1.3, sd.shape)) ** 2))
    return heads


def _cycle(fn, frames):
    it = itertools.cycle(frames)
    return lambda: fn(next(it))


def figures():
    from threadpoolctl import threadpool_limits

    from lidar_quality_core.mimo.clustering import dbscan_pairs, dbscan_sklearn, neighbour_pairs
    from lidar_quality_core.mimo.merging import HeadDetections, MergeConfig, merge_heads

    cfg = MergeConfig()
    with threadpool_limits(limits=1):
        for K, name in ((4, "mimo.merge_ms"), (2, "mimo.merge_k2_ms")):
            frames = [[HeadDetections(*h) for h in synthetic_heads(K, s)] for s in range(N_FRAMES)]
            yield name, _cycle(lambda f: merge_heads(f, cfg), frames), "percentiles"
        for K in (2, 4):
            pooled = [np.concatenate([h[0] for h in synthetic_heads(K, s)])
                      for s in range(N_FRAMES)]
            pairs = [(len(b), *neighbour_pairs(b, cfg.eps)) for b in pooled]
            ms = cfg.min_samples(K)
            yield f"mimo.pairs_k{K}_ms", _cycle(lambda b: neighbour_pairs(b, cfg.eps), pooled)
            yield f"mimo.dbscan_own_k{K}_ms", _cycle(lambda p, m=ms: dbscan_pairs(*p, m), pairs)
            yield (f"mimo.dbscan_sklearn_k{K}_ms",
                   _cycle(lambda p, m=ms: dbscan_sklearn(*p, m, cfg.eps), pairs))


if __name__ == "__main__":
    import time

    for item in figures():
        t = []
        for _ in range(100):
            t0 = time.perf_counter()
            item[1]()
            t.append((time.perf_counter() - t0) * 1e3)
        print(f"{item[0]:32s} p50 {np.median(t):7.3f} ms  p99 {np.percentile(t, 99):7.3f} ms")
