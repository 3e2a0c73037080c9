"""Tiny perception bags for tests: simulated sequences (HDL-64 beams, few columns) written
as simulator bags and run through the real reference perception."""
from pathlib import Path


def simulated_perception_bags(root: Path, perception, *, n_sequences: int, n_frames: int,
                              seed: int, columns: int) -> Path:
    """``root/bags/seq_NN`` for ``n_sequences`` sequences of ``n_frames`` 64 x ``columns``
    scans, perceived by ``perception`` (a ``reference_perception.cli.Perception``)."""
    from lidar_sim import classes
    from lidar_sim.bag import SimBagWriter
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64
    from reference_perception.cli import process_bag

    root.mkdir(parents=True, exist_ok=True)
    for s in range(n_sequences):
        sim = root / f"sim_{s:02d}"
        with SimBagWriter(sim) as bag:
            for f in sequence_frames(seed * 100 + s, n_frames, cfg=hdl64(columns=columns)):
                bag.write_frame(f.stamp_ns, xyz=f.xyz, intensity=f.intensity, ring=f.ring,
                                label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                                gt_class_names=[classes.class_name(c) for c in f.gt_class],
                                gt_ids=[str(k) for k in f.gt_instance])
        process_bag(sim, root / "bags" / f"seq_{s:02d}", perception, quiet=True)
    return root / "bags"
