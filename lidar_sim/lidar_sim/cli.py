"""``lidar-sim generate``: simulated sequences written as rosbag2, KITTI and SemanticKITTI.

    python -m lidar_sim generate --sequences 4 --frames 100 --seed 7 --out data/sim

Deterministic for a given seed and version: sequence s uses seed ``seed * 1000 + s`` for
its scene and its sensor noise. Layout of ``--out``::

    bags/seq_NN/                 rosbag2 (see lidar_sim.bag)
    kitti/training/...           KITTI object dataset, frame id = SSFFFF (sequence, frame)
    kitti/ImageSets/{train,val}.txt   split by sequence (the last --val-sequences are val)
    semantickitti/sequences/NN/  SemanticKITTI, plus semantickitti/semantic-kitti.yaml
    annotated/                   with --annotation-errors: the "as annotated" ground truth
                                 (kitti label_2, SemanticKITTI labels) and errors.jsonl
    summary.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from . import classes, kitti, semantickitti
from .annotation_errors import (AnnotationErrorConfig, apply_records, config_dict,
                                inject_box_errors, inject_region_errors)
from .bag import SimBagWriter
from .sensor import hdl32, hdl64, vls128
from .sequence import generate_sequence
from .simulate import simulate_frame

SENSORS = {"hdl64": hdl64, "hdl32": hdl32, "vls128": vls128}
#: Plausible annotator confusions between our classes (by name).
CONFUSIONS = {"car": ["truck"], "truck": ["car"], "pedestrian": ["cyclist"], "cyclist": ["pedestrian"]}
REGION_CLASSES = ["road", "sidewalk", "terrain", "vegetation", "building"]


def _progress(done: int, total: int, t0: float) -> None:
    width = 30
    fill = int(width * done / max(total, 1))
    rate = done / max(time.monotonic() - t0, 1e-9)
    sys.stderr.write(f"\r[{'#' * fill}{'.' * (width - fill)}] {done}/{total} frames "
                     f"({rate:.1f} frames/s)")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def generate(out: Path, *, sequences: int, frames: int, seed: int, sensor: str = "hdl64",
             storage: str = "mcap", val_sequences: int = 1, annotation_errors: bool = False,
             quiet: bool = False) -> dict:
    out = Path(out)
    cfg = SENSORS[sensor]()
    confusions = {classes.class_id(k): [classes.class_id(v) for v in vs] for k, vs in CONFUSIONS.items()}
    region_classes = [classes.class_id(n) for n in REGION_CLASSES]
    err_cfg = AnnotationErrorConfig()
    (out / "semantickitti").mkdir(parents=True, exist_ok=True)
    classes.semantickitti_class_map(out / "semantickitti" / "semantic-kitti.yaml")
    splits = {"train": [], "val": []}
    stats = {"points": [], "objects": Counter(), "labelled_kitti": 0, "errors": Counter()}
    errors_file = None
    if annotation_errors:
        (out / "annotated").mkdir(parents=True, exist_ok=True)
        (out / "annotated" / "config.json").write_text(json.dumps(config_dict(err_cfg), indent=2))
        errors_file = open(out / "annotated" / "errors.jsonl", "w")
    t0 = time.monotonic()
    total = sequences * frames
    try:
        for s in range(sequences):
            seq = generate_sequence(seed * 1000 + s, frames)
            rng = np.random.default_rng(seed * 1000 + s)
            err_rng = np.random.default_rng([seed, s, 7])
            split = "val" if s >= sequences - val_sequences and sequences > val_sequences else "train"
            poses, stamps = [], []
            with SimBagWriter(out / "bags" / f"seq_{s:02d}", storage=storage, frame_id="lidar") as bag:
                for i in range(frames):
                    f = simulate_frame(seq.frame(i, max_range=cfg.max_range), cfg, rng, sequence=s)
                    names = [classes.class_name(c) for c in f.gt_class]
                    bag.write_frame(f.stamp_ns, xyz=f.xyz, intensity=f.intensity, ring=f.ring,
                                    label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                                    gt_class_names=names, gt_ids=[str(k) for k in f.gt_instance])
                    frame_id = f"{s:02d}{i:04d}"
                    visible = f.gt_num_points > 0  # KITTI labels objects the sensor saw
                    stats["labelled_kitti"] += kitti.write_frame(
                        out / "kitti", frame_id, f.xyz, f.intensity, f.gt_boxes[visible],
                        [f.gt_kitti_type[k] for k in np.flatnonzero(visible)],
                        f.gt_occlusion[visible], calib=kitti.SIM_CALIB)
                    splits[split].append(frame_id)
                    semantickitti.write_scan(out / "semantickitti", s, i, f.xyz, f.intensity,
                                             classes.to_semantickitti(f.semantic), f.instance)
                    poses.append(f.ego_pose)
                    stamps.append((f.stamp_ns - seq.start_ns) * 1e-9)
                    stats["points"].append(len(f.xyz))
                    stats["objects"].update(names)
                    if errors_file is not None:
                        # only boxes that reach the label files can carry an applied error
                        visible &= kitti.in_image(f.gt_boxes, calib=kitti.SIM_CALIB)
                        recs = (inject_box_errors(f.gt_boxes[visible], f.gt_class[visible],
                                                  f.gt_instance[visible], confusions, err_rng, err_cfg)
                                + inject_region_errors(f.xyz, f.semantic, region_classes, err_rng, err_cfg))
                        a_boxes, a_cls, a_inst, a_lab = apply_records(
                            recs, f.gt_boxes[visible], f.gt_class[visible], f.gt_instance[visible],
                            f.xyz, f.semantic)
                        row_of = {int(k): j for j, k in enumerate(f.gt_instance)}
                        row = [row_of[int(k)] for k in a_inst]
                        # keep the object's own KITTI type (Van vs Truck) unless its class changed
                        types = [f.gt_kitti_type[j] if c == f.gt_class[j] else classes.kitti_type(c)
                                 for j, c in zip(row, a_cls)]
                        kitti.write_frame(out / "annotated" / "kitti", frame_id, f.xyz, f.intensity,
                                          a_boxes, types, f.gt_occlusion[row],
                                          calib=kitti.SIM_CALIB)
                        semantickitti.write_scan(out / "annotated" / "semantickitti", s, i, f.xyz,
                                                 f.intensity, classes.to_semantickitti(a_lab), f.instance)
                        for r in recs:
                            errors_file.write(json.dumps({"sequence": s, "frame": i,
                                                          "kitti_frame_id": frame_id, **r}) + "\n")
                            stats["errors"][r["kind"]] += 1
                    if not quiet:
                        _progress(s * frames + i + 1, total, t0)
            semantickitti.write_sequence_meta(out / "semantickitti", s, np.array(poses), np.array(stamps))
    finally:
        if errors_file is not None:
            errors_file.close()
    kitti.write_image_sets(out / "kitti", splits)
    wall = time.monotonic() - t0
    pts = np.array(stats["points"])
    summary = {
        "sequences": sequences, "frames": int(len(pts)), "seed": seed, "sensor": sensor,
        "points_per_frame": {"mean": float(pts.mean()), "min": int(pts.min()), "max": int(pts.max())},
        "objects_per_class": dict(sorted(stats["objects"].items())),
        "kitti_labels": stats["labelled_kitti"],
        "annotation_errors": dict(stats["errors"]),
        "wall_time_s": round(wall, 2), "frames_per_s": round(len(pts) / wall, 2),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lidar-sim", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate", help="simulate sequences and write the datasets")
    g.add_argument("--sequences", type=int, default=4)
    g.add_argument("--frames", type=int, default=100)
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--sensor", choices=sorted(SENSORS), default="hdl64")
    g.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    g.add_argument("--val-sequences", type=int, default=1)
    g.add_argument("--annotation-errors", action="store_true",
                   help="also write an 'as annotated' ground truth with listed injected errors")
    g.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.sequences < 1 or args.frames < 1:
        ap.error("--sequences and --frames must be >= 1")
    summary = generate(args.out, sequences=args.sequences, frames=args.frames, seed=args.seed,
                       sensor=args.sensor, storage=args.storage, val_sequences=args.val_sequences,
                       annotation_errors=args.annotation_errors, quiet=args.quiet)
    p = summary["points_per_frame"]
    print(f"{summary['frames']} frames in {summary['sequences']} sequence(s), "
          f"{p['mean']:.0f} points/frame (min {p['min']}, max {p['max']}), "
          f"{summary['wall_time_s']} s ({summary['frames_per_s']} frames/s)")
    print("objects per class (frame-wise): " +
          ", ".join(f"{k} {v}" for k, v in summary["objects_per_class"].items()))
    if summary["annotation_errors"]:
        print("injected annotation errors: " +
              ", ".join(f"{k} {v}" for k, v in summary["annotation_errors"].items()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
