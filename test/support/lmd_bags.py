"""Tiny perception bags of ``lidar_quality_core.synthetic`` frames (LMD dataset / training /
evaluation tests): cloud, post-NMS detections, pre-NMS proposals and ground truth on the
reference perception topics, one bag per sequence."""
import numpy as np
from lidar_quality_core import synthetic
from lidar_quality_core.boxes import arrays_to_detections
from lidar_quality_ros.bag_io import BagWriter
from lmd_frames import frame_messages, header

TOPICS = {"points": ("/lidar/points", "sensor_msgs/msg/PointCloud2"),
          "detections": ("/perception/detections", "vision_msgs/msg/Detection3DArray"),
          "proposals": ("/perception/proposals", "vision_msgs/msg/Detection3DArray"),
          "gt_objects": ("/lidar/gt_objects", "vision_msgs/msg/Detection3DArray")}


def gt_message(h, f):
    names = [synthetic.CLASS_NAMES[c] for c in f.gt_classes]
    return arrays_to_detections(h, f.gt_boxes, names, np.ones(len(names)),
                                ids=[str(100 + i) for i in range(len(names))])


def write_bag(path, seeds, *, n_points=12_000, n_objects=10, n_proposals=100, n_fp=4,
              first_sec=1):
    """One bag, one frame per seed (stamps ``first_sec``, ``first_sec + 1``, ...); returns
    ``[(frame, (cloud, detections, proposals, gt), stamp_ns), ...]``."""
    out = []
    with BagWriter(path) as w:
        for k, seed in enumerate(seeds):
            sec = first_sec + k
            f = synthetic.synthetic_frame(n_points=n_points, n_objects=n_objects,
                                          n_proposals=n_proposals, seed=seed)
            cloud, dets, props = frame_messages(f, sec, n_fp=n_fp)
            gt = gt_message(header(sec), f)
            stamp = sec * 1_000_000_000
            for key, msg in zip(("points", "detections", "proposals", "gt_objects"),
                                (cloud, dets, props, gt)):
                topic, msgtype = TOPICS[key]
                w.write(topic, msgtype, stamp, msg)
            out.append((f, (cloud, dets, props, gt), stamp))
    return out


def write_split(root, n_bags, frames_per_bag, *, seed0=0, **kw):
    """``root/seq_00 .. seq_{n-1}`` bags with distinct seeds; returns {bag path: frames}."""
    root.mkdir(parents=True, exist_ok=True)
    out = {}
    for b in range(n_bags):
        seeds = [seed0 + 100 * b + k for k in range(frames_per_bag)]
        p = root / f"seq_{b:02d}"
        out[p] = write_bag(p, seeds, **kw)
    return out
