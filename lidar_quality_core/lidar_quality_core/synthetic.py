"""Small deterministic synthetic lidar frames for tests and benchmarks.

Frame convention: the lidar sensor is at the origin, the ground plane is at
``z = -SENSOR_HEIGHT``; boxes are ``(x, y, z, l, w, h, yaw)`` with ``(x, y, z)`` the
box centre.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .conventions import wrap_angle as _wrap

__all__ = ["SyntheticFrame", "synthetic_frame", "SENSOR_HEIGHT", "CLASS_NAMES"]

SENSOR_HEIGHT = 1.8
CLASS_NAMES = ("car", "pedestrian", "cyclist")

N_RINGS = 64
_ELEV_DEG = (-24.9, 2.0)  # HDL-64-like vertical field of view
_MAX_GROUND_RANGE = 120.0
# class -> mean (l, w, h) and prior probability
_SIZE_MEAN = np.array([[4.5, 1.85, 1.6], [0.8, 0.7, 1.75], [1.8, 0.7, 1.7]])
_SIZE_STD = np.array([[0.3, 0.1, 0.1], [0.1, 0.08, 0.1], [0.15, 0.08, 0.1]])
_CLASS_P = np.array([0.7, 0.15, 0.15])


@dataclass(frozen=True)
class SyntheticFrame:
    """One synthetic frame; all box arrays are float64 (N, 7)."""

    points: np.ndarray        # (M, 3) float32
    intensity: np.ndarray     # (M,) float32 in [0, 1]
    gt_boxes: np.ndarray      # (n_objects, 7)
    gt_classes: np.ndarray    # (n_objects,) int64 index into CLASS_NAMES
    detections: np.ndarray    # (n_objects, 7) noisy copies of gt_boxes (same order)
    det_scores: np.ndarray    # (n_objects,)
    det_classes: np.ndarray   # (n_objects,)
    proposals: np.ndarray     # (n_proposals, 7) pre-NMS proposals
    prop_scores: np.ndarray   # (n_proposals,)
    prop_classes: np.ndarray  # (n_proposals,)
    prop_object: np.ndarray   # (n_proposals,) source object index, -1 for background


def _sample_sizes(rng, classes):
    sz = _SIZE_MEAN[classes] + rng.standard_normal((len(classes), 3)) * _SIZE_STD[classes]
    return np.maximum(sz, 0.2)


def _place_objects(rng, n):
    """Centres in a 5-60 m annulus with >= 7 m spacing (rejection over a bounded pool)."""
    n_cand = max(20 * n, 1)
    r = np.sqrt(rng.uniform(5.0**2, 60.0**2, n_cand))
    a = rng.uniform(-np.pi, np.pi, n_cand)
    cand = np.column_stack([r * np.cos(a), r * np.sin(a)])
    accepted: list[int] = []
    for i in range(n_cand):
        if len(accepted) == n:
            break
        if not accepted or np.min(np.sum((cand[accepted] - cand[i]) ** 2, axis=1)) >= 49.0:
            accepted.append(i)
    if len(accepted) < n:  # crowded request: allow overlaps rather than fail
        rest = np.setdiff1d(np.arange(n_cand), accepted)[: n - len(accepted)]
        accepted.extend(rest.tolist())
    return cand[np.asarray(accepted, dtype=np.int64)] if n else np.zeros((0, 2))


def _ray_box_t(dirs, box):
    """Entry distance of rays from the origin into ``box`` (inf when missed)."""
    c, s = np.cos(box[6]), np.sin(box[6])
    o = -box[:3]
    o_loc = np.array([c * o[0] + s * o[1], -s * o[0] + c * o[1], o[2]])
    d_loc = np.column_stack([c * dirs[:, 0] + s * dirs[:, 1],
                             -s * dirs[:, 0] + c * dirs[:, 1], dirs[:, 2]])
    half = box[3:6] / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o_loc) / d_loc
        t2 = (half - o_loc) / d_loc
    tn = np.max(np.minimum(t1, t2), axis=1)
    tf = np.min(np.maximum(t1, t2), axis=1)
    hit = (tn <= tf) & (tn > 0.0)  # NaN (ray parallel on a face) -> no hit
    return np.where(hit, tn, np.inf)


def _noisy(rng, boxes, sxy, sz, srel, syaw):
    out = boxes.copy()
    n = len(boxes)
    out[:, 0:2] += rng.standard_normal((n, 2)) * sxy
    out[:, 2] += rng.standard_normal(n) * sz
    out[:, 3:6] *= np.clip(1.0 + rng.standard_normal((n, 3)) * srel, 0.5, 1.5)
    out[:, 6] = _wrap(out[:, 6] + rng.standard_normal(n) * syaw)
    return out


def synthetic_frame(n_points: int = 120_000, n_objects: int = 50, n_proposals: int = 500,
                    seed: int = 0) -> SyntheticFrame:
    """Deterministic frame: rotating-lidar points, gt boxes, detections and proposals.

    Points come from a 64-ring scan (column-major, exactly ``n_points``): ground hits up to
    120 m, hits on the object boxes' surfaces, and far clutter for rays with no hit.
    """
    rng = np.random.default_rng(seed)
    n_points, n_objects, n_proposals = int(n_points), int(n_objects), int(n_proposals)

    classes = rng.choice(3, size=n_objects, p=_CLASS_P).astype(np.int64)
    sizes = _sample_sizes(rng, classes)
    xy = _place_objects(rng, n_objects)
    gt = np.column_stack([xy, -SENSOR_HEIGHT + sizes[:, 2] / 2.0, sizes,
                          rng.uniform(-np.pi, np.pi, n_objects)]).reshape(n_objects, 7)

    # --- scan pattern ---
    n_cols = max(-(-n_points // N_RINGS), 1)
    elev = np.deg2rad(np.linspace(*_ELEV_DEG, N_RINGS))
    dth = 2.0 * np.pi / n_cols
    col = np.arange(n_points) // N_RINGS
    ring = np.arange(n_points) % N_RINGS
    az = col * dth - np.pi + rng.uniform(-0.1, 0.1, n_points) * dth
    el = elev[ring]
    ce = np.cos(el)
    dirs = np.column_stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)])

    with np.errstate(divide="ignore"):
        t = np.where(el < 0, SENSOR_HEIGHT / -np.sin(el), np.inf)
    t[t > _MAX_GROUND_RANGE] = np.inf
    hit_obj = np.full(n_points, -1, dtype=np.int64)
    # Only rays within each object's azimuth span are tested (bounded loop over objects).
    for k in range(n_objects):
        b = gt[k]
        c, s = np.cos(b[6]), np.sin(b[6])
        lc = np.array([1, -1, -1, 1]) * b[3] / 2
        wc = np.array([1, 1, -1, -1]) * b[4] / 2
        corner_az = np.arctan2(b[1] + s * lc + c * wc, b[0] + c * lc - s * wc)
        a0 = np.arctan2(b[1], b[0])
        rel = _wrap(corner_az - a0)
        lo = int(np.floor((a0 + rel.min() + np.pi) / dth)) - 1
        hi = int(np.ceil((a0 + rel.max() + np.pi) / dth)) + 1
        cols = np.arange(lo, hi + 1) % n_cols
        idx = (cols[:, None] * N_RINGS + np.arange(N_RINGS)[None, :]).ravel()
        idx = idx[idx < n_points]
        tk = _ray_box_t(dirs[idx], b)
        closer = tk < t[idx]
        t[idx[closer]] = tk[closer]
        hit_obj[idx[closer]] = k

    ground = np.isfinite(t) & (hit_obj < 0)
    clutter = ~np.isfinite(t)
    t[clutter] = rng.uniform(30.0, 100.0, int(clutter.sum()))
    t = t + rng.standard_normal(n_points) * 0.02
    points = (dirs * t[:, None]).astype(np.float32)

    refl = np.append(rng.uniform(0.3, 0.9, n_objects), 0.0)  # [-1] -> padding entry
    inten = np.where(hit_obj >= 0, refl[hit_obj] * np.exp(-t / 80.0),
                     np.where(ground, 0.25 * np.exp(-t / 40.0), rng.uniform(0.0, 0.5, n_points)))
    inten = np.clip(inten + rng.standard_normal(n_points) * 0.02, 0.0, 1.0).astype(np.float32)

    # --- detections: one noisy copy per object ---
    dets = _noisy(rng, gt, 0.15, 0.05, 0.05, 0.05)
    rng_xy = np.hypot(gt[:, 0], gt[:, 1])
    det_scores = np.clip(0.95 - 0.005 * rng_xy + rng.standard_normal(n_objects) * 0.05,
                         0.05, 1.0)

    # --- proposals: several per object plus some background ---
    n_bg = n_proposals if n_objects == 0 else int(round(0.1 * n_proposals))
    n_cl = n_proposals - n_bg
    src = np.arange(n_cl) % max(n_objects, 1)
    cl = _noisy(rng, gt[src], 0.4, 0.1, 0.1, 0.15) if n_cl else np.zeros((0, 7))
    err = (np.hypot(*(cl[:, :2] - gt[src, :2]).T) if n_cl else np.zeros(0))
    cl_scores = np.clip(0.9 * np.exp(-err) + rng.standard_normal(n_cl) * 0.05, 0.01, 1.0)
    bg_cls = rng.choice(3, size=n_bg, p=_CLASS_P).astype(np.int64)
    r = np.sqrt(rng.uniform(5.0**2, 70.0**2, n_bg))
    a = rng.uniform(-np.pi, np.pi, n_bg)
    bg_sz = _sample_sizes(rng, bg_cls)
    bg = np.column_stack([r * np.cos(a), r * np.sin(a), -SENSOR_HEIGHT + bg_sz[:, 2] / 2,
                          bg_sz, rng.uniform(-np.pi, np.pi, n_bg)]).reshape(n_bg, 7)
    bg_scores = rng.uniform(0.01, 0.4, n_bg)
    perm = rng.permutation(n_proposals)  # interleave so order carries no information
    proposals = np.concatenate([cl, bg])[perm]
    prop_scores = np.concatenate([cl_scores, bg_scores])[perm]
    prop_classes = np.concatenate([classes[src] if n_cl else np.zeros(0, np.int64),
                                   bg_cls])[perm]
    prop_object = np.concatenate([src, np.full(n_bg, -1)]).astype(np.int64)[perm]

    return SyntheticFrame(points=points, intensity=inten, gt_boxes=gt, gt_classes=classes,
                          detections=dets, det_scores=det_scores, det_classes=classes.copy(),
                          proposals=proposals, prop_scores=prop_scores,
                          prop_classes=prop_classes, prop_object=prop_object)
