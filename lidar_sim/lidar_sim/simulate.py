"""One simulated frame: a sequence frame's primitives scanned by the sensor, with the
per-object ground truth a dataset needs (points inside, occlusion, truncation)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import raycast
from .primitives import Primitives
from .sensor import SensorConfig, beam_directions, scan
from .sequence import FramePrimitives


@dataclass
class SimFrame:
    """Points (column-major, sensor frame) with their labels, and ground-truth objects.

    ``gt_num_points``: points labelled with the object's instance. ``gt_occlusion`` in
    [0, 1]: 1 - visible points / beams that would hit the object were it alone (dropouts
    count as occlusion; 1 for an object no beam reaches). ``gt_truncation`` in [0, 1]:
    share of the box's corners outside the sensor's vertical field of view or range.
    """

    sequence: int
    index: int
    stamp_ns: int
    ego_pose: np.ndarray
    xyz: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    gt_boxes: np.ndarray
    gt_class: np.ndarray
    gt_instance: np.ndarray
    gt_kitti_type: tuple
    gt_num_points: np.ndarray
    gt_occlusion: np.ndarray
    gt_truncation: np.ndarray


def _object_parts(prims: Primitives, instance: int) -> Primitives:
    keep = prims.box_instance == instance
    return Primitives(boxes=prims.boxes[keep], box_class=prims.box_class[keep],
                      box_instance=prims.box_instance[keep],
                      box_reflectivity=prims.box_reflectivity[keep], ground_z=None)


def unoccluded_beams(prims: Primitives, cfg: SensorConfig, gt_boxes: np.ndarray,
                     gt_instance: np.ndarray) -> np.ndarray:
    """Beams that would hit each object's parts if it were alone in the scene.

    Only the beams inside the object's angular window are cast (a bounded loop over the
    frame's objects), against the object's own parts. The window is the ray caster's own
    culling interval of the GT box (the parts lie inside it): exact for boxes seen edge-on
    from close by (the nearest point of a side, not a corner, bounds the elevation) and
    for a sensor inside the footprint (full circle, +-90 deg).
    """
    out = np.zeros(len(gt_boxes), dtype=np.int64)
    if not len(gt_boxes):
        return out
    dirs = beam_directions(cfg)                       # (rings, columns, 3)
    az = np.arctan2(dirs[0, :, 1], dirs[0, :, 0])     # per column
    el = np.arcsin(np.clip(dirs[:, 0, 2], -1, 1))     # per ring
    boxes = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 7)
    kind = raycast._Kind(raycast.KIND_BOX, boxes, None, None, None)
    # no ground: the window must hold every beam the parts could stop, whatever is below
    obj, a0, a1, e0, e1 = raycast._intervals(kind, np.zeros(3), np.inf, cfg.max_range)
    col_in = (az >= a0[:, None]) & (az <= a1[:, None])  # (intervals, columns): seam splits
    ring_in = (el >= e0[:, None]) & (el <= e1[:, None])
    for k in np.unique(obj):
        rows = obj == k
        cols = np.flatnonzero(col_in[rows].any(axis=0))
        rings = np.flatnonzero(ring_in[rows][0])
        if not len(cols) or not len(rings):
            continue
        sub = dirs[np.ix_(rings, cols)].reshape(-1, 3)
        hits = raycast.cast(_object_parts(prims, int(gt_instance[k])), np.zeros(3), sub,
                            cfg.max_range)
        # misses come back with t = inf: count real hits only (the scan drops returns
        # nearer than min_range)
        out[k] = int((hits.hit & (hits.t >= cfg.min_range)).sum())
    return out


def truncation(cfg: SensorConfig, gt_boxes: np.ndarray) -> np.ndarray:
    """Share of each box's 8 corners outside the vertical field of view or max range."""
    from lidar_quality_core.box_geometry import corners_3d

    if not len(gt_boxes):
        return np.zeros(0)
    c = corners_3d(gt_boxes)
    rng_xy = np.hypot(c[..., 0], c[..., 1])
    el = np.degrees(np.arctan2(c[..., 2], rng_xy))
    e = np.asarray(cfg.elevations_deg)
    outside = (el > e.max()) | (el < e.min()) | (np.linalg.norm(c, axis=-1) > cfg.max_range)
    return outside.mean(axis=1)


def simulate_frame(fp: FramePrimitives, cfg: SensorConfig, rng, *, sequence: int = 0) -> SimFrame:
    """Scan ``fp`` with ``cfg`` and derive the per-object ground truth."""
    s = scan(fp.primitives, cfg, rng)
    inst_row = {int(k): i for i, k in enumerate(fp.gt_instance)}
    counts = np.zeros(len(fp.gt_instance), dtype=np.int64)
    if len(fp.gt_instance):
        found, n = np.unique(s.instance[s.instance > 0], return_counts=True)
        for k, c in zip(found.tolist(), n.tolist()):
            if k in inst_row:
                counts[inst_row[k]] = c
    expected = unoccluded_beams(fp.primitives, cfg, fp.gt_boxes, fp.gt_instance)
    occl = np.where(expected > 0, 1.0 - counts / np.maximum(expected, 1), 1.0)
    return SimFrame(sequence=sequence, index=fp.index, stamp_ns=fp.stamp_ns, ego_pose=fp.ego_pose,
                    xyz=s.xyz, intensity=s.intensity, ring=s.ring, semantic=s.semantic,
                    instance=s.instance, gt_boxes=fp.gt_boxes, gt_class=fp.gt_class,
                    gt_instance=fp.gt_instance, gt_kitti_type=fp.gt_kitti_type,
                    gt_num_points=counts, gt_occlusion=np.clip(occl, 0.0, 1.0),
                    gt_truncation=truncation(cfg, fp.gt_boxes))
