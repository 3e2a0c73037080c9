"""Tiny LidarMetaSeg training data for tests: simulated scans (HDL-64 beams, few columns)
segmented by the real reference segmenter, as perception bags or a SemanticKITTI-style
directory with per-scan probabilities."""
from pathlib import Path

import numpy as np

COLUMNS = 512  # 64 x 512 scans: ~30k points, quick to simulate and to segment


def _frames(seed: int, n_frames: int):
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64

    return list(sequence_frames(seed, n_frames, cfg=hdl64(columns=COLUMNS)))


def perception_bags(root: Path, n_sequences: int = 2, n_frames: int = 4, seed: int = 5) -> Path:
    """``root/bags/seq_NN``: perception bags (points, points_gt, segmentation) of
    ``n_sequences`` simulated sequences."""
    from reference_perception.cli import Perception

    from perception_bags import simulated_perception_bags

    return simulated_perception_bags(root, Perception(detector=False, segmenter=True, heads=0),
                                     n_sequences=n_sequences, n_frames=n_frames, seed=seed,
                                     columns=COLUMNS)


def semantickitti_dir(root: Path, n_frames: int = 3, seed: int = 9, sequence: int = 8,
                      unlabeled_beyond: float | None = 30.0) -> Path:
    """``root/sequences/NN/{velodyne,labels,probabilities}`` of one simulated sequence;
    points farther than ``unlabeled_beyond`` metres are labelled unlabeled (raw id 0)."""
    from lidar_sim.classes import to_semantickitti
    from lidar_sim.semantickitti import sequence_dir, write_scan
    from reference_perception.segmenter import ReferenceSegmenter

    seg = ReferenceSegmenter.load()
    prob_dir = sequence_dir(root, sequence) / "probabilities"
    prob_dir.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(_frames(seed, n_frames)):
        sem = to_semantickitti(f.semantic)
        if unlabeled_beyond is not None:
            sem[np.linalg.norm(f.xyz, axis=1) > unlabeled_beyond] = 0
        write_scan(root, sequence, i, f.xyz, f.intensity, sem, f.instance)
        p = seg.predict_proba(f.xyz, f.intensity).astype(np.float32)
        np.save(prob_dir / f"{i:06d}.npy", p)
    return root


def train_node_models(out_dir: Path, frames, settings) -> tuple:
    """Real LMS meta models for node tests: XGBoost fitted on the metrics and IoU_adj
    targets of ``frames`` (simulated scans with noisy probabilities, ``lms_scans``) under
    ``settings``, saved as ``out_dir/lms_{classifier,regressor}.joblib`` with ``settings``
    recorded as ``lms-train`` records them. Returns the two paths."""
    from lidar_quality_core import meta_model
    from lms_ros.pipeline import decode, frame_metrics
    from lidar_quality_core.lms.targets import segment_targets

    from lms_scans import frame_cloud, frame_probs

    X, y = [], []
    for i, f in enumerate(frames):
        res = frame_metrics(decode(frame_cloud(f, frame_probs(f, 100 * i)), settings), settings)
        _, adj = segment_targets(res, f.semantic)
        ok = np.isfinite(adj)
        X.append(res.features[ok])
        y.append(adj[ok])
    X, y = np.concatenate(X), np.concatenate(y)
    clf = meta_model.fit_estimator("xgboost", "classification", X, (y > 0).astype(int))
    reg = meta_model.fit_estimator("xgboost", "regression", X, y)
    return meta_model.save_pair(out_dir, "lms", clf, reg, settings.metric_names(),
                                training_data={"source": "lms_scans frames",
                                               **meta_model.settings_record(settings, "lms")})
