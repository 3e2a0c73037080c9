"""lms_node frame work without DDS: ``lms.node_frame_ms`` (p50 / p99; goal p99 <= 70 ms).

One ``LmsProcessor.process`` call, the body of the node's frame callback: decode the
cloud (one simulated HDL-64 frame, ~120k points, x, y, z, intensity, ring and 14 float32
probability fields), check / renormalize the probabilities, all LidarMetaSeg metrics on
the 64 x 2048 image (:func:`lidar_quality_core.lms.segment_metrics.compute_segments`), meta classifier
and regressor on the kept segments, and the output messages (annotated PointCloud2 and
the SegmentQualityArray of every segment). ``lms.node_frame_uint8_ms``: the same with
uint8-quantized probability fields. Markers are built only while someone subscribes and
are not timed.

Probabilities: those of ``bench_lms_metrics.bench_frame`` restricted to the simulator's
14 classes (softmax over their logits; errors in connected blobs, ~2k segments, ~190
kept). Models: the shipped ``models/lms/lms_*`` when present, else XGBoost models of the
shipped kind and size (``meta_model.make_estimator`` defaults) fitted here on the
metrics of three noise draws of the frame. One thread (BLAS and XGBoost limited to 1).
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from lidar_quality_core import meta_model
from lidar_quality_core.pointcloud import create_cloud
from lms_ros.pipeline import (LmsProcessor, LmsSettings, decode, default_model_paths,
                              frame_metrics, probability_field)
from lidar_quality_core.lms.targets import segment_targets
from std_msgs.msg import Header

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_lms_metrics import bench_frame  # noqa: E402 - a sibling script: bench/ must be on sys.path first

SETTINGS = LmsSettings(ring_zero_top=True)   # lidar_sim: ring 0 = top beam


def frame_message(seed: int = 11, *, quantize: bool = False, n_points: int | None = None):
    """(cloud message, semantic labels) of the bench frame with 14-class probabilities;
    ``n_points``: that many of its points (fewer: a random subset; more: the frame repeated
    with 1 cm jitter, a denser scan of the same scene)."""
    xyz, probs20, ring, inten, sem, _ = bench_frame(seed)
    if n_points is not None:
        rng = np.random.default_rng(seed)
        idx = (np.sort(rng.choice(len(xyz), n_points, replace=False)) if n_points <= len(xyz)
               else np.arange(n_points) % len(xyz))
        jitter = np.where((np.arange(n_points) >= len(xyz))[:, None],
                          rng.normal(0, 0.01, (n_points, 3)), 0.0)
        xyz, probs20, ring = xyz[idx] + jitter, probs20[idx], ring[idx]
        inten, sem = inten[idx], sem[idx]
    n = len(SETTINGS.class_names)
    p = probs20[:, :n] / probs20[:, :n].sum(axis=1, keepdims=True)
    if quantize:
        p = np.rint(p * 255).astype(np.uint8)
    else:
        p = p.astype(np.float32)
    h = Header(frame_id="lidar_top")
    h.stamp.sec = 1
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
            "intensity": inten.astype(np.float32), "ring": ring.astype(np.uint16)}
    for k, c in enumerate(SETTINGS.class_names):
        cols[probability_field(c)] = p[:, k]
    return create_cloud(h, cols), sem


def _models(tmp):
    paths = default_model_paths()
    if not all(p.is_file() for p in paths):
        X, y = [], []
        for seed in (11, 12, 13):
            msg, sem = frame_message(seed)
            res = frame_metrics(decode(msg, SETTINGS), SETTINGS)
            _, adj = segment_targets(res, sem)
            ok = np.isfinite(adj)
            X.append(res.features[ok])
            y.append(adj[ok])
        X, y = np.concatenate(X), np.concatenate(y)
        clf = meta_model.fit_estimator("xgboost", "classification", X, (y > 0).astype(int))
        reg = meta_model.fit_estimator("xgboost", "regression", X, y)
        paths = meta_model.save_pair(tmp, "lms", clf, reg, SETTINGS.metric_names())
    return meta_model.MetaModels(*paths, SETTINGS.metric_names())


def figures():
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(limits=1):
        proc = LmsProcessor(SETTINGS, _models(tmp))
        msg, _ = frame_message()
        msg8, _ = frame_message(quantize=True)
        yield ("lms.node_frame_ms", lambda: proc.process(msg), "percentiles")
        yield ("lms.node_frame_uint8_ms", lambda: proc.process(msg8), "percentiles")
        # cost against the cloud size (30k, 120k, 250k points ~ VLS-128), same image
        for n, tag in ((30_000, "30k"), (120_000, "120k"), (250_000, "250k")):
            m, _ = frame_message(n_points=n)
            yield f"lms.node_frame_{tag}_ms", lambda m=m: proc.process(m), "percentiles"


if __name__ == "__main__":
    import cProfile
    import pstats
    import time

    for name, fn, _ in figures():
        out = fn()
        r = out.result
        print(f"{name}: {len(out.inp)} points, {r.n_segments} segments, {len(r.kept_ids)} "
              f"kept, renormalized {out.inp.n_renormalized}")
        t = []
        for _ in range(30):
            t0 = time.perf_counter()
            fn()
            t.append((time.perf_counter() - t0) * 1e3)
        print(f"{name}: p50 {np.percentile(t, 50):.1f} ms, p99 {np.percentile(t, 99):.1f} ms")
        if "--profile" in sys.argv:
            pr = cProfile.Profile()
            pr.enable()
            for _ in range(10):
                fn()
            pr.disable()
            pstats.Stats(pr).sort_stats("tottime").print_stats(15)
