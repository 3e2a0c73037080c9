"""LidarMetaSeg metrics figure: ``lms.metrics_ms`` (reported as ``_p50`` / ``_p99``) =
:func:`lidar_quality_core.lms.segment_metrics.compute_segments` (projection, fill, heatmaps, segments,
all 86 + 2n metrics, point maps) on one simulated HDL-64 frame (64 x 2048, ~120k points,
ring field) with 20-class probabilities, on ONE thread (target p50 <= 25 ms, p99 <= 50).

Probabilities: softmax of noisy logits around the frame's semantic labels, padded from the
simulator's 14 classes to 20. The noise has a per-point part and a part shared by
patches of the range image (4 rings x 32 columns), so that errors come in connected
blobs as with a real network: 92 % point accuracy, ~2.8k segments (~240 with SP >= 10),
close to the reference segmenter on a frame of the same simulator (92 %, 2.3k, 210).
"""
from __future__ import annotations

import numpy as np

N_CLASSES = 20


def bench_frame(seed: int = 11):
    """(xyz, probs (N, 20) float32, ring, intensity, semantic, cfg) of one frame."""
    from lidar_quality_core.lms.projection import RangeImageConfig
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64

    f = next(sequence_frames(seed, 1))
    s = hdl64()
    cfg = RangeImageConfig.from_elevations(s.elevations_deg, s.columns)
    rng = np.random.default_rng(seed)
    n = len(f.xyz)
    az = np.arctan2(f.xyz[:, 1], f.xyz[:, 0])
    col = (np.floor(0.5 * (1.0 - az / np.pi) * cfg.cols).astype(np.int64)) % cfg.cols
    patch = (f.ring.astype(np.int64) // 4) * (cfg.cols // 32) + col // 32
    n_patch = (cfg.rows // 4 + 1) * (cfg.cols // 32)
    logits = rng.normal(0.0, 0.35, (n, N_CLASSES)).astype(np.float32)
    logits += 1.25 * rng.normal(0.0, 1.0, (n_patch, N_CLASSES)).astype(np.float32)[patch]
    logits[np.arange(n), f.semantic] += 4.5
    probs = np.exp(logits - logits.max(axis=1, keepdims=True))
    probs /= probs.sum(axis=1, keepdims=True)
    return f.xyz, probs.astype(np.float32), f.ring, f.intensity, f.semantic, cfg


def figures():
    from threadpoolctl import threadpool_limits

    from lidar_quality_core.lms.segment_metrics import compute_segments

    xyz, probs, ring, inten, _, cfg = bench_frame()
    # one BLAS thread only while this figure is timed (run.py times it before resuming us)
    with threadpool_limits(limits=1):
        yield ("lms.metrics_ms",
               lambda: compute_segments(xyz, probs, cfg, ring=ring, intensity=inten),
               "percentiles")


if __name__ == "__main__":
    import time

    from lidar_quality_core.lms.segment_metrics import compute_segments

    xyz, probs, ring, inten, sem, cfg = bench_frame()
    res = compute_segments(xyz, probs, cfg, ring=ring, intensity=inten)
    print(f"{len(xyz)} points, accuracy {(res.point_class == sem).mean():.3f}, "
          f"{res.n_segments} segments, {len(res.kept_ids)} kept")
    for name, fn, _ in figures():
        t = []
        for _ in range(50):
            t0 = time.perf_counter()
            fn()
            t.append((time.perf_counter() - t0) * 1e3)
        print(f"{name}: p50 {np.percentile(t, 50):.1f} ms, p99 {np.percentile(t, 99):.1f} ms")
