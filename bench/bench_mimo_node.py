"""mimo_node frame figures: decode to output messages inside the node, without DDS
(what ``MimoNode`` does per frame; one thread).

Frames: ``bench_mimo_merge.synthetic_heads`` (100 boxes per head, K heads, log-probability
logits over background + 4 classes, predicted variances) turned into the reference
perception's messages (``detection_array`` with the foreground probabilities and the
pose covariance, ``box_variance_array``), serialized. Models: the shipped ``models/mimo``
pair if present, else an xgboost pair of the same kind and size (``meta_model.
make_estimator`` defaults: 300 trees, depth 4) fitted on these frames' features with
stand-in targets (only the cost matters here). Each repetition processes the next of 20
frames.

Figures (ms, p50 / p99):
* ``mimo.node_frame_ms``: K = 2 x 100 boxes: the heads' and variances' bytes decoded as
  the node's raw subscriptions do (``detection_cdr``, ``box_variance_cdr``),
  ``pipeline.process_frame`` (merge, features, meta models; detections encoded to bytes
  as the node publishes them, ``detection_cdr.encode_detections``, and the uncertainty
  message, ``cluster_uncertainty_cdr``) (goal p99 <= 10 ms); ``mimo.node_frame_k4_ms``:
  the same for K = 4 x 100;
* medians of the parts for K = 2: ``mimo.node_decode_ms`` (bytes to ``HeadDetections``
  of all heads, variances included), ``mimo.node_merge_ms`` (``merge_heads`` +
  features), ``mimo.node_predict_ms`` (``MetaModels.predict``), ``mimo.node_messages_ms``
  (``output_messages`` with both messages as bytes, as the node publishes them),
  ``mimo.node_objects_ms`` (the same as message objects, both serialized: what encoding
  the bytes directly saves), and
  ``mimo.node_markers_ms`` (``box_markers``: built only while output/markers has a
  subscriber, so not in the frame figure).
"""
from __future__ import annotations

import importlib.util
import itertools
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
N_FRAMES = 20


def _merge_bench():
    spec = importlib.util.spec_from_file_location("bench_mimo_merge", HERE / "bench_mimo_merge.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _messages(K: int, seed: int):
    """(header, head messages, variance messages) of one frame."""
    from reference_perception.messages import box_variance_array, detection_array
    from std_msgs.msg import Header

    from mimo_ros.pipeline import DEFAULT_CLASS_NAMES

    h = Header(frame_id="lidar")
    h.stamp.sec = 100 + seed
    heads, variances = [], []
    for b, lg, v in _merge_bench().synthetic_heads(K, seed):
        ids = list(range(len(b)))
        heads.append(detection_array(h, b, np.exp(lg)[:, 1:], DEFAULT_CLASS_NAMES, ids=ids,
                                     variances=v))
        variances.append(box_variance_array(h, v, ids=ids))
    return h, heads, variances


def _serialized(frame):
    from rclpy.serialization import serialize_message

    h, heads, variances = frame
    return ([serialize_message(m) for m in heads], [serialize_message(m) for m in variances])


def _node_frame(data, settings, models):
    """Bytes in, bytes out: one frame of the node (module docstring)."""
    from lidar_quality_core.box_variance_cdr import decode_box_variance_array
    from lidar_quality_core.detection_cdr import decode_detection_array

    from mimo_ros.pipeline import process_frame

    heads = [decode_detection_array(b) for b in data[0]]
    variances = [decode_box_variance_array(b) for b in data[1]]
    out = process_frame(heads[0].header, heads, variances, settings, models, serialized=True,
                        serialized_uncertainty=True)
    return out.detections, out.uncertainty


def _models(settings, frames):
    from lidar_quality_core.meta_model import MetaModels, fit_estimator, save_pair

    from mimo_ros.pipeline import STAT_FEATURES, default_model_paths, frame_features

    c, r = default_model_paths(settings.use_points)
    if c.exists() and r.exists():
        return MetaModels(c, r, settings.feature_names())
    X = np.vstack([frame_features(hd, v, settings).features for _, hd, v in frames])
    size, score = X[:, STAT_FEATURES.index("cluster_size")], X[:, STAT_FEATURES.index("score")]
    y_iou = np.clip(score - 0.1 * np.nan_to_num(X[:, STAT_FEATURES.index("mutual_information")]),
                    0, 1)
    clf = fit_estimator("xgboost", "classification", X, ((size >= 2) & (score > 0.6)).astype(float))
    reg = fit_estimator("xgboost", "regression", X, y_iou)
    out = Path(tempfile.mkdtemp(prefix="bench_mimo_node_"))
    c, r = save_pair(out, "mimo", clf, reg, settings.feature_names())
    return MetaModels(c, r, settings.feature_names())


def _cycle(fn, items):
    it = itertools.cycle(items)
    return lambda: fn(next(it))


def figures():
    from lidar_quality_core.box_variance_cdr import decode_box_variance_array
    from lidar_quality_core.detection_cdr import decode_detection_array
    from rclpy.serialization import serialize_message
    from threadpoolctl import threadpool_limits

    from lidar_quality_ros.markers import box_markers
    from lidar_quality_core.mimo.merging import merge_heads
    from mimo_ros.pipeline import (MimoSettings, cluster_features, frame_features,
                                   head_detections, output_messages)

    with threadpool_limits(limits=1):
        for K, name in ((2, "mimo.node_frame_ms"), (4, "mimo.node_frame_k4_ms")):
            s = MimoSettings(num_heads=K)
            frames = [_messages(K, seed) for seed in range(N_FRAMES)]
            m = _models(s, frames)
            data = [_serialized(f) for f in frames]
            yield name, _cycle(lambda d, s=s, m=m: _node_frame(d, s, m), data), "percentiles"
            if K != 2:
                continue
            yield "mimo.node_decode_ms", _cycle(
                lambda d: [head_detections(decode_detection_array(b),
                                           decode_box_variance_array(v), s)
                           for b, v in zip(*d)], data)
            decoded = [[head_detections(d, v, s)[0] for d, v in zip(f[1], f[2])] for f in frames]
            yield "mimo.node_merge_ms", _cycle(
                lambda hd: cluster_features(merge_heads(hd, s.merge), s, K), decoded)
            done = [frame_features(f[1], f[2], s) for f in frames]
            yield "mimo.node_predict_ms", _cycle(lambda fr: m.predict(fr.features), done)
            preds = [(f[0], fr, *m.predict(fr.features)) for f, fr in zip(frames, done)]
            yield "mimo.node_messages_ms", _cycle(
                lambda p: output_messages(*p, serialized=True, serialized_uncertainty=True),
                preds)
            yield "mimo.node_objects_ms", _cycle(
                lambda p: [serialize_message(x) for x in output_messages(*p)], preds)
            yield "mimo.node_markers_ms", _cycle(
                lambda p: box_markers(p[0], p[1].merge.boxes, p[2],
                                      [f"{c} {x:.2f}" for c, x in zip(p[1].class_labels(),
                                                                      p[2].tolist())]), preds)


if __name__ == "__main__":
    import time

    for item in figures():
        t = []
        for _ in range(100):
            t0 = time.perf_counter()
            item[1]()
            t.append((time.perf_counter() - t0) * 1e3)
        print(f"{item[0]:32s} p50 {np.median(t):7.3f} ms  p99 {np.percentile(t, 99):7.3f} ms")
