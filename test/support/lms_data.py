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
    """``root/seq_NN``: perception bags (points, points_gt, segmentation) of
    ``n_sequences`` simulated sequences."""
    from lidar_sim import classes
    from lidar_sim.bag import SimBagWriter
    from reference_perception.cli import Perception, process_bag

    perception = Perception(detector=False, segmenter=True, heads=0)
    root.mkdir(parents=True, exist_ok=True)
    for s in range(n_sequences):
        sim = root / f"sim_{s:02d}"
        with SimBagWriter(sim) as bag:
            for f in _frames(seed * 100 + s, n_frames):
                bag.write_frame(f.stamp_ns, xyz=f.xyz, intensity=f.intensity, ring=f.ring,
                                label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                                gt_class_names=[classes.class_name(c) for c in f.gt_class],
                                gt_ids=[str(k) for k in f.gt_instance])
        process_bag(sim, root / "bags" / f"seq_{s:02d}", perception, quiet=True)
    return root / "bags"


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
