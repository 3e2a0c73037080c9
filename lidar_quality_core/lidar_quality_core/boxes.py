"""vision_msgs/Detection3DArray <-> numpy box arrays.

Box rows are ``x, y, z, l, w, h, yaw`` with (x, y, z) the box centre, as in
``BoundingBox3D.center`` (see ``box_geometry``). Yaw comes from any quaternion (ZYX Euler
angles); roll and pitch are reported, not applied, because lidar boxes are upright.
Messages are read field by field (a bounded loop over detections); everything else is
vectorized. No rclpy: only the message classes are imported, lazily where needed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw")


def quaternion_to_rpy(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions ``x, y, z, w`` (any norm > 0) -> (N, 3) roll, pitch, yaw (ZYX)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        x, y, z, w = (q / norm).T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=1)


def yaw_to_quaternion(yaw: np.ndarray) -> np.ndarray:
    """Yaw angles (N,) -> (N, 4) quaternions ``x, y, z, w`` of a rotation about +z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64).reshape(-1)
    zeros = np.zeros_like(half)
    return np.stack([zeros, zeros, np.sin(half), np.cos(half)], axis=1)


@dataclass
class DetectionArrays:
    """Numpy view of a Detection3DArray; row ``i`` is detection ``i`` of the message.

    ``valid[i]`` is False when the box cannot be used (``reasons[i]`` says why); such
    rows keep whatever numbers they had so that outputs can still be matched to inputs.
    ``class_scores`` maps class id -> (N,) score of that hypothesis (NaN when absent).
    """

    boxes: np.ndarray
    scores: np.ndarray
    labels: list[str]
    ids: list[str]
    roll_pitch: np.ndarray
    valid: np.ndarray
    reasons: list[str]
    class_scores: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.labels)


def detections_to_arrays(detections) -> DetectionArrays:
    """Convert a Detection3DArray (or a sequence of Detection3D) to arrays.

    Class and score are those of the highest-scoring hypothesis. A detection is invalid
    with a reason for: no hypothesis, a non-finite value in centre / size / orientation /
    score, a size <= 0, a zero quaternion.
    """
    dets = list(getattr(detections, "detections", detections))
    n = len(dets)
    raw = np.empty((n, 11))
    scores = np.full(n, np.nan)
    labels, ids, reasons = [""] * n, [""] * n, [""] * n
    hyps: dict[str, np.ndarray] = {}
    for i, det in enumerate(dets):
        c, o, s = det.bbox.center.position, det.bbox.center.orientation, det.bbox.size
        raw[i] = (c.x, c.y, c.z, s.x, s.y, s.z, o.x, o.y, o.z, o.w, 0.0)
        ids[i] = det.id
        best = -np.inf
        for r in det.results:
            cls, sc = r.hypothesis.class_id, r.hypothesis.score
            hyps.setdefault(cls, np.full(n, np.nan))[i] = sc
            if sc > best or not labels[i] and best == -np.inf:
                best, labels[i] = sc, cls
        if det.results:
            scores[i] = best
        else:
            reasons[i] = "no hypothesis in results"
    quat = raw[:, 6:10]
    rpy = quaternion_to_rpy(quat) if n else np.zeros((0, 3))
    boxes = np.concatenate([raw[:, :6], rpy[:, 2:3]], axis=1)
    finite = np.isfinite(raw[:, :10]).all(axis=1)
    checks = [
        (~np.isfinite(raw[:, :3]).all(axis=1), "non-finite centre"),
        (~np.isfinite(raw[:, 3:6]).all(axis=1), "non-finite size"),
        (np.isfinite(raw[:, 3:6]).all(axis=1) & (raw[:, 3:6] <= 0).any(axis=1), "size <= 0"),
        (~np.isfinite(quat).all(axis=1), "non-finite orientation"),
        (finite & (np.linalg.norm(np.where(np.isfinite(quat), quat, 0), axis=1) < 1e-9),
         "zero quaternion"),
        (~np.isfinite(scores) & np.array([bool(d.results) for d in dets], dtype=bool),
         "non-finite score"),
    ]
    for bad, why in checks:
        for i in np.flatnonzero(bad):
            reasons[i] = f"{reasons[i]}; {why}" if reasons[i] else why
    valid = np.array([not r for r in reasons], dtype=bool)
    return DetectionArrays(boxes=boxes, scores=scores, labels=labels, ids=ids,
                           roll_pitch=rpy[:, :2], valid=valid, reasons=reasons,
                           class_scores=hyps)


def arrays_to_detections(header, boxes: np.ndarray, labels, scores, *, ids=None,
                         class_scores: dict[str, np.ndarray] | None = None,
                         covariance_diagonal: np.ndarray | None = None):
    """Build a Detection3DArray (one result per detection, or one per finite entry of
    ``class_scores``, highest score first); ``covariance_diagonal`` (N, 6) fills the pose
    covariance diagonal (x, y, z, roll, pitch, yaw)."""
    from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose

    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    quat = yaw_to_quaternion(boxes[:, 6])
    out = Detection3DArray(header=header)
    for i, b in enumerate(boxes.tolist()):
        det = Detection3D(header=header, id=str(ids[i]) if ids is not None else str(i))
        p, o, s = det.bbox.center.position, det.bbox.center.orientation, det.bbox.size
        p.x, p.y, p.z = b[0], b[1], b[2]
        s.x, s.y, s.z = b[3], b[4], b[5]
        o.x, o.y, o.z, o.w = quat[i].tolist()
        items = (sorted(((c, float(v[i])) for c, v in class_scores.items() if np.isfinite(v[i])),
                        key=lambda cs: -cs[1])
                 if class_scores else [(str(labels[i]), float(scores[i]))])
        for cls, sc in items:
            hyp = ObjectHypothesisWithPose()
            hyp.hypothesis.class_id, hyp.hypothesis.score = cls, sc
            hyp.pose.pose = det.bbox.center
            if covariance_diagonal is not None:
                cov = np.zeros((6, 6))
                np.fill_diagonal(cov, covariance_diagonal[i])
                hyp.pose.covariance = cov.reshape(-1)
            det.results.append(hyp)
        out.detections.append(det)
    return out
