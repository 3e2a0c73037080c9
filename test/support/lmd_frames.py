"""LMD test frames: messages of a ``lidar_quality_core.synthetic`` frame, IoU targets, and
small real meta models trained on them (pipeline and node tests)."""
import numpy as np
from lidar_quality_core import synthetic
from lidar_quality_core.iou import iou_bev
from lidar_quality_core.pointcloud import create_xyz_cloud
from reference_perception.messages import detection_array
from std_msgs.msg import Header

CLASS_NAMES = ("car", "truck", "pedestrian", "cyclist")


def header(sec, frame_id="lidar_top", nanosec=0):
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = int(sec), int(nanosec)
    return h


def class_probs(classes, scores):
    """Per-class hypothesis scores: the synthetic class gets ``score``, the others a fifth
    of it each (so the top hypothesis is the detection's score)."""
    idx = np.array([CLASS_NAMES.index(synthetic.CLASS_NAMES[c]) for c in classes], dtype=int)
    p = np.repeat(np.asarray(scores, dtype=float)[:, None] * 0.2, len(CLASS_NAMES), axis=1)
    p[np.arange(len(idx)), idx] = scores
    return p


def frame_messages(f, sec, *, n_fp=5, frame_id="lidar_top"):
    """(cloud, detections, proposals) of synthetic frame ``f``: detections are the noisy
    object copies plus the ``n_fp`` highest-scoring background proposals (false
    positives); proposals carry ids ``p<k>``, detections ``d<sec>_<i>``."""
    h = header(sec, frame_id)
    cloud = create_xyz_cloud(h, f.points, f.intensity)
    bg = np.flatnonzero(f.prop_object < 0)
    bg = bg[np.argsort(-f.prop_scores[bg], kind="stable")][:n_fp]
    boxes = np.concatenate([f.detections, f.proposals[bg]])
    scores = np.concatenate([f.det_scores, f.prop_scores[bg]])
    classes = np.concatenate([f.det_classes, f.prop_classes[bg]])
    dets = detection_array(h, boxes, class_probs(classes, scores), CLASS_NAMES,
                           ids=[f"d{sec}_{i}" for i in range(len(boxes))])
    props = detection_array(h, f.proposals, class_probs(f.prop_classes, f.prop_scores),
                            CLASS_NAMES, ids=[f"p{k}" for k in range(len(f.proposals))])
    return cloud, dets, props


def iou_targets(boxes, gt_boxes):
    """IoU_BEV of each box with its best ground-truth box (0 without ground truth)."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    if not len(gt_boxes) or not len(boxes):
        return np.zeros(len(boxes))
    return np.nan_to_num(iou_bev(boxes, gt_boxes).max(axis=1), nan=0.0)


def train_models(out_dir, settings, n_frames=6, seed=100, record_settings=False,
                 profile=False):
    """Fit an XGBoost classifier (TP iff IoU_BEV >= 0.5) and regressor (IoU_BEV) on
    ``pipeline.frame_features`` of small synthetic frames and save them with
    ``meta_model.save_pair`` as ``lmd_<mode>_*``; returns (classifier, regressor) paths.
    ``record_settings``: record ``settings`` in the manifests as lmd-train does (else an
    older manifest without them); ``profile``: record the training data's domain profile as
    lmd-train does."""
    from lidar_quality_core import meta_model
    from lmd_ros.pipeline import frame_features

    X, y, scores, boxes, points = [], [], [], [], []
    for k in range(n_frames):
        f = synthetic.synthetic_frame(n_points=20_000, n_objects=15, n_proposals=150,
                                      seed=seed + k)
        cloud, dets, props = frame_messages(f, k + 1)
        fr = frame_features(cloud, None if settings.proposal_mode == "exact" else dets,
                            None if settings.proposal_mode == "none" else props, settings)
        X.append(fr.features[fr.valid])
        y.append(iou_targets(fr.detections.boxes[fr.valid], f.gt_boxes))
        scores.append(fr.detections.scores[fr.valid])
        boxes.append(int(fr.valid.sum()))
        points.append(fr.n_points)
    X, y = np.concatenate(X), np.concatenate(y)
    clf = meta_model.fit_estimator("xgboost", "classification", X, (y >= 0.5).astype(float))
    reg = meta_model.fit_estimator("xgboost", "regression", X, y)
    training = {"source": "lidar_quality_core.synthetic", "frames": n_frames, "seed": seed}
    if record_settings:
        training.update(meta_model.settings_record(settings, "lmd"))
    prof = meta_model.training_profile(X, settings.feature_names(), {
        "detector score": np.concatenate(scores), "points per frame": points}) \
        if profile else None
    return meta_model.save_pair(out_dir, f"lmd_{settings.proposal_mode}", clf, reg,
                                settings.feature_names(), training_data=training,
                                domain_profile=prof)
