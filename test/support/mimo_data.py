"""Tiny LiDAR-MIMO test data: simulated sequences (HDL-64 beams, 1024 columns) run through
the real reference multi-head detector into perception bags (points, points_gt,
gt_objects, head_k, head_k/variance)."""
from pathlib import Path

COLUMNS = 1024  # 64 x 1024 scans: ~65k points, ~40 detections per head


def perception_bags(root: Path, n_sequences: int = 2, n_frames: int = 3, seed: int = 7,
                    heads: int = 2) -> Path:
    """``root/bags/seq_NN``: multi-head perception bags of ``n_sequences`` sequences."""
    from reference_perception.cli import Perception

    from perception_bags import simulated_perception_bags

    return simulated_perception_bags(root, Perception(detector=False, segmenter=False,
                                                      heads=heads),
                                     n_sequences=n_sequences, n_frames=n_frames, seed=seed,
                                     columns=COLUMNS)


def head_frames(n_frames: int = 6, K: int = 2, seed: int = 0, n_obj: int = 12):
    """Synthetic multi-head frames: ``[(gt boxes, heads, variances, cloud), ...]``. Every
    head sees each ground-truth car with p = 0.85 with per-object noise (so IoUs vary),
    three ghost cars without ground truth (false positives every head agrees on) and two
    false positives of its own; predicted variances follow the noise."""
    import numpy as np
    from lidar_quality_core.pointcloud import create_xyz_cloud
    from reference_perception.messages import box_variance_array, detection_array
    from std_msgs.msg import Header

    from mimo_ros.pipeline import DEFAULT_CLASS_NAMES

    frames = []
    for i in range(n_frames):
        rng = np.random.default_rng([seed, i])
        h = Header(frame_id="lidar")
        h.stamp.sec = 100 + i
        gx, gy = np.meshgrid(np.arange(4) * 9.0 + 8.0, np.arange(3) * 7.0 - 7.0)
        gt = np.column_stack([gx.ravel()[:n_obj], gy.ravel()[:n_obj], np.full(n_obj, -0.9),
                              np.full(n_obj, 4.3), np.full(n_obj, 1.8), np.full(n_obj, 1.5),
                              rng.uniform(-np.pi, np.pi, n_obj)])
        ghosts = np.column_stack([np.arange(3) * 9.0 + 12.5, np.full(3, -10.5),
                                  np.full(3, -0.9), np.full((3, 3), [4.0, 1.8, 1.5]),
                                  rng.uniform(-3, 3, 3)])
        objects = np.vstack([gt, ghosts])
        sd = rng.uniform(0.02, 0.6, len(objects))
        heads, variances = [], []
        for k in range(K):
            seen = np.flatnonzero(np.r_[rng.random(n_obj) < 0.85, np.ones(3, bool)])
            b = objects[seen].copy()
            b[:, :2] += rng.normal(0, 1, (len(seen), 2)) * sd[seen, None]
            fp = np.column_stack([rng.uniform(5, 40, 2), rng.uniform(-12, 12, 2),
                                  np.full(2, -0.9), np.full((2, 3), [4.0, 1.8, 1.5]),
                                  rng.uniform(-3, 3, 2)])
            boxes = np.vstack([b, fp])
            p_car = np.r_[rng.uniform(0.5, 0.95, len(seen)), rng.uniform(0.2, 0.5, 2)]
            fg = np.column_stack([p_car, (1 - p_car) * 0.3, (1 - p_car) * 0.2,
                                  (1 - p_car) * 0.1])
            var = np.r_[sd[seen], 0.5, 0.5][:, None] ** 2 * [1, 1, 0.2, 0.1, 0.05, 0.05, 0.1]
            ids = [f"{i}-{k}-{j}" for j in range(len(boxes))]
            heads.append(detection_array(h, boxes, fg, DEFAULT_CLASS_NAMES, ids=ids,
                                         variances=var))
            variances.append(box_variance_array(h, var, ids=ids))
        xyz = np.vstack([gt[:, :3] + rng.uniform(-0.8, 0.8, (n_obj, 3)) for _ in range(10)]
                        + [rng.uniform(-40, 40, (1000, 3))]).astype(np.float32)
        cloud = create_xyz_cloud(h, xyz, rng.random(len(xyz)).astype(np.float32))
        frames.append((gt, heads, variances, cloud))
    return frames


def train_node_models(out_dir: Path, settings, frames) -> tuple:
    """Real MIMO meta models for node tests: XGBoost fitted on the merged clusters of
    ``frames`` (:func:`head_frames`) under ``settings`` (target: BEV IoU with the best
    ground-truth box), saved as ``out_dir/mimo[_points]_{classifier,regressor}.joblib``
    with ``settings`` recorded as ``mimo-train`` records them. Returns the two paths."""
    import numpy as np
    from lidar_quality_core import meta_model
    from lidar_quality_core.iou import iou_bev

    from mimo_ros.pipeline import frame_features

    X, y = [], []
    for gt, heads, variances, cloud in frames:
        f = frame_features(heads, variances, settings, cloud)
        X.append(f.features)
        y.append(iou_bev(f.merge.boxes, gt).max(axis=1) if len(f) else np.zeros(0))
    X, y = np.vstack(X), np.concatenate(y)
    clf = meta_model.fit_estimator("xgboost", "classification", X, (y >= 0.5).astype(float))
    reg = meta_model.fit_estimator("xgboost", "regression", X, y)
    prefix = "mimo_points" if settings.use_points else "mimo"
    return meta_model.save_pair(out_dir, prefix, clf, reg, settings.feature_names(),
                                training_data={"source": "mimo_data.head_frames",
                                               **meta_model.settings_record(settings, "mimo")})
