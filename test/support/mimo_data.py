"""Tiny LiDAR-MIMO test data: simulated sequences (HDL-64 beams, 1024 columns) run through
the real reference multi-head detector into perception bags (points, points_gt,
gt_objects, head_k, head_k/variance)."""
from pathlib import Path

COLUMNS = 1024  # 64 x 1024 scans: ~65k points, ~40 detections per head


def perception_bags(root: Path, n_sequences: int = 2, n_frames: int = 3, seed: int = 7,
                    heads: int = 2) -> Path:
    """``root/bags/seq_NN``: multi-head perception bags of ``n_sequences`` sequences."""
    from lidar_sim import classes
    from lidar_sim.bag import SimBagWriter
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64
    from reference_perception.cli import Perception, process_bag

    perception = Perception(detector=False, segmenter=False, heads=heads)
    root.mkdir(parents=True, exist_ok=True)
    for s in range(n_sequences):
        sim = root / f"sim_{s:02d}"
        with SimBagWriter(sim) as bag:
            for f in sequence_frames(seed * 100 + s, n_frames, cfg=hdl64(columns=COLUMNS)):
                bag.write_frame(f.stamp_ns, xyz=f.xyz, intensity=f.intensity, ring=f.ring,
                                label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                                gt_class_names=[classes.class_name(c) for c in f.gt_class],
                                gt_ids=[str(k) for k in f.gt_instance])
        process_bag(sim, root / "bags" / f"seq_{s:02d}", perception, quiet=True)
    return root / "bags"
