"""lmd_node frame work without DDS: ``lmd.node_frame_ms`` (p50 / p99; goal p99 <= 15 ms).

What the node does per frame from the received bytes to the messages it publishes: the
cloud (120k points) read from its bytes (``cloud_cdr``; until 2026-11-29 deserialized by
rclpy, as the node then took it), the 50 detections and 500 proposals
(reference-perception layout: one hypothesis per class, 4 classes) decoded from their
serialized bytes (``detection_cdr``), as the node's raw subscriptions do, then one
``LmdProcessor.process`` call, the body of the node's frame callback: features
(threshold mode), meta classifier and regressor, the re-scored output detections
(serialized bytes) and the DetectionQualityArray (bytes too, as the node publishes it).
Markers are built only while someone subscribes to them, so they are timed apart:
``lmd.node_frame_markers_ms`` (the same plus the MarkerArray). ``lmd.node_frame_exact_ms``:
exact mode (the node runs NMS over the 500 proposals itself; IoU 0.1, score >= 0.1; the
survivors are scored).

Models: the shipped ``models/lmd/lmd_<mode>_*`` when present, else XGBoost models of
the shipped kind and size (``meta_model.make_estimator`` defaults) fitted here on a few
synthetic frames. One thread (BLAS and XGBoost limited to 1).
"""
from __future__ import annotations

import tempfile

import numpy as np
from threadpoolctl import threadpool_limits

from lidar_quality_core import meta_model, synthetic
from lidar_quality_core.cloud_cdr import decode_point_cloud
from lidar_quality_core.detection_cdr import decode_detection_array
from lidar_quality_core.iou import iou_bev
from lidar_quality_core.pointcloud import create_xyz_cloud
from lmd_ros.pipeline import LmdProcessor, LmdSettings, default_model_paths, frame_features
from reference_perception.messages import detection_array
from std_msgs.msg import Header

CLASSES = LmdSettings().class_names
N_DET, N_PROP = 50, 500


def _messages(n_points, n_det, n_prop, seed, sec=1):
    """(cloud, detections, proposals, gt boxes): proposals = the detections + jittered
    copies + background, the top class carrying the score."""
    f = synthetic.synthetic_frame(n_points=n_points, n_objects=n_det,
                                  n_proposals=n_prop - n_det, seed=seed)
    h = Header(frame_id="lidar_top")
    h.stamp.sec = sec
    remap = np.array([CLASSES.index(c) for c in synthetic.CLASS_NAMES])

    def probs(cls, scores):
        p = np.repeat(scores[:, None] * 0.2, len(CLASSES), axis=1)
        p[np.arange(len(cls)), remap[cls]] = scores
        return p

    pb = np.concatenate([f.detections, f.proposals])
    ps = np.concatenate([f.det_scores, f.prop_scores])
    pc = np.concatenate([f.det_classes, f.prop_classes])
    dets = detection_array(h, f.detections, probs(f.det_classes, f.det_scores), CLASSES,
                           ids=list(range(n_det)))
    props = detection_array(h, pb, probs(pc, ps), CLASSES)
    return create_xyz_cloud(h, f.points, f.intensity), dets, props, f.gt_boxes


def _models(settings, tmp):
    paths = default_model_paths(settings.proposal_mode)
    if not all(p.is_file() for p in paths):
        X, y = [], []
        for seed in range(100, 106):
            cloud, dets, props, gt = _messages(20_000, 15, 150, seed)
            fr = frame_features(cloud, dets, props, settings)
            X.append(fr.features)
            y.append(iou_bev(fr.detections.boxes, gt).max(axis=1))
        X, y = np.concatenate(X), np.concatenate(y)
        clf = meta_model.fit_estimator("xgboost", "classification", X, (y >= 0.5) * 1.0)
        reg = meta_model.fit_estimator("xgboost", "regression", X, y)
        paths = meta_model.save_pair(tmp, f"lmd_{settings.proposal_mode}", clf, reg,
                                     settings.feature_names())
    return meta_model.MetaModels(*paths, settings.feature_names())


def figures():
    from rclpy.serialization import serialize_message

    tmp = tempfile.TemporaryDirectory(prefix="bench_lmd_node_")
    cloud, dets, props, _ = _messages(120_000, N_DET, N_PROP, seed=0)
    wire = [serialize_message(m) for m in (cloud, dets, props)]

    def inputs():
        """What the node's subscriptions hand over: the cloud and the detection arrays read
        from their bytes (cloud_cdr, detection_cdr)."""
        return (decode_point_cloud(wire[0]), decode_detection_array(wire[1]),
                decode_detection_array(wire[2]))

    with threadpool_limits(limits=1):
        s = LmdSettings(proposal_mode="threshold")
        proc = LmdProcessor(s, _models(s, tmp.name), serialized_quality=True)
        yield "lmd.node_frame_ms", lambda: proc.process(*inputs()), "percentiles"
        yield ("lmd.node_frame_markers_ms", lambda: proc.process(*inputs(), markers=True),
               "percentiles")
        se = LmdSettings(proposal_mode="exact")
        proc_e = LmdProcessor(se, _models(se, tmp.name), serialized_quality=True)

        def frame_exact():
            c, _, p = inputs()
            return proc_e.process(c, None, p)
        yield "lmd.node_frame_exact_ms", frame_exact, "percentiles"
        # cost against the cloud size (30k, 120k, 250k points ~ VLS-128), same boxes
        for n, tag in ((30_000, "30k"), (120_000, "120k"), (250_000, "250k")):
            w = [serialize_message(m) for m in _messages(n, N_DET, N_PROP, seed=0)[:3]]

            def sized(w=w):
                return proc.process(decode_point_cloud(w[0]),
                                    decode_detection_array(w[1]), decode_detection_array(w[2]))
            yield f"lmd.node_frame_{tag}_ms", sized, "percentiles"
    tmp.cleanup()
