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
