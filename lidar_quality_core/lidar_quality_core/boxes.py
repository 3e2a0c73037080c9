"""vision_msgs/Detection3DArray <-> numpy box arrays.

Box rows are ``x, y, z, l, w, h, yaw`` with (x, y, z) the box centre, as in
``BoundingBox3D.center`` (see ``box_geometry``). Yaw comes from any quaternion (ZYX Euler
angles); roll and pitch are not applied, because lidar boxes are upright: they are kept in
``DetectionArrays.roll_pitch``, and :func:`tilt_issue` words the warning the processors
raise when a box is tilted by more than :data:`TILT_TOLERANCE_DEG` (the box is kept).
Messages are read field by field (a bounded loop over detections); everything else is
vectorized. No rclpy: only the message classes are imported, lazily where needed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw")
#: |roll| or |pitch| above this [deg] is reported: float32 quaternions of upright boxes
#: stay far below it, a detector that really tilts its boxes far above.
TILT_TOLERANCE_DEG = 1.0


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

    def tilt_deg(self) -> np.ndarray:
        """(N,) larger of |roll| and |pitch| of each box [deg] (NaN for a non-finite
        orientation)."""
        return np.degrees(np.abs(self.roll_pitch).max(axis=1)) if len(self) else np.zeros(0)


def tilt_issue(arrays: DetectionArrays, what: str = "boxes",
               tolerance_deg: float = TILT_TOLERANCE_DEG) -> str | None:
    """``"3 of 12 boxes have roll/pitch up to 30.0 deg: only yaw is used"`` when valid
    boxes of ``arrays`` are tilted by more than ``tolerance_deg``, else None."""
    tilt = arrays.tilt_deg()
    with np.errstate(invalid="ignore"):
        bad = arrays.valid & (tilt > tolerance_deg)
    n = int(np.count_nonzero(bad))
    if not n:
        return None
    return (f"{n} of {len(arrays)} {what} have roll/pitch up to {tilt[bad].max():.1f} deg: "
            "only yaw is used (boxes are read as upright)")


def detections_to_arrays(detections) -> DetectionArrays:
    """Convert a Detection3DArray (or a sequence of Detection3D) to arrays.

    Class and score are those of the highest-scoring hypothesis. A detection is invalid
    with a reason for: no hypothesis, a non-finite value in centre / size / orientation /
    score, a size <= 0, a zero quaternion.
    """
    dets = list(getattr(detections, "detections", detections))
    rows, ids = [], []
    hyp_det, hyp_cls, hyp_sc = [], [], []
    for i, det in enumerate(dets):
        bb = det.bbox
        c, o, s = bb.center.position, bb.center.orientation, bb.size
        rows.append((c.x, c.y, c.z, s.x, s.y, s.z, o.x, o.y, o.z, o.w))
        ids.append(det.id)
        for r in det.results:
            h = r.hypothesis
            hyp_det.append(i)
            hyp_cls.append(h.class_id)
            hyp_sc.append(h.score)
    raw = np.array(rows, dtype=np.float64).reshape(len(dets), 10)
    return arrays_from_fields(raw, ids, hyp_det, hyp_cls, hyp_sc)


def arrays_from_fields(raw: np.ndarray, ids: list[str], hyp_det, hyp_cls, hyp_score
                       ) -> DetectionArrays:
    """DetectionArrays from fields already read out of the detections (of messages, or of
    serialized bytes: ``detection_cdr``), so that both share one set of rules.

    ``raw`` (N, 10): centre x y z, size x y z, quaternion x y z w; ``ids`` (N); one entry
    per hypothesis, in message order: ``hyp_det`` (its detection), ``hyp_cls`` (class
    names, or ``(codes, names)`` with names in order of first appearance), ``hyp_score``.
    The top hypothesis of a detection is its first one, replaced by any later one scoring
    strictly higher (a NaN first score stays; a later NaN never wins).
    """
    n = len(raw)
    det = np.asarray(hyp_det, dtype=np.int64).reshape(-1)
    sc = np.asarray(hyp_score, dtype=np.float64).reshape(-1)
    n_hyp = len(det)
    if isinstance(hyp_cls, tuple):
        codes, names = np.asarray(hyp_cls[0], dtype=np.int64).reshape(-1), list(hyp_cls[1])
    else:
        lut: dict[str, int] = {}
        codes = np.fromiter((lut.setdefault(c, len(lut)) for c in hyp_cls), np.int64,
                            count=n_hyp)
        names = list(lut)
    hyps: dict[str, np.ndarray] = {}
    for k, name in enumerate(names):
        m = codes == k
        col = np.full(n, np.nan)
        col[det[m]] = sc[m]  # a class given twice in one detection: the last one
        hyps[name] = col
    has = np.bincount(det, minlength=n)[:n] > 0 if n_hyp else np.zeros(n, dtype=bool)
    top = np.zeros(n, dtype=np.int64)
    if n_hyp:
        first = np.zeros(n, dtype=np.int64)
        first[det[::-1]] = np.arange(n_hyp - 1, -1, -1)
        # highest score, earliest on ties; NaN sorts last
        order = np.lexsort((np.arange(n_hyp), -np.where(np.isnan(sc), -np.inf, sc), det))
        top[has] = order[np.searchsorted(det[order], np.flatnonzero(has))]
        nan_first = has & np.isnan(sc[first])
        top[nan_first] = first[nan_first]
    scores = np.where(has, sc[top] if n_hyp else np.nan, np.nan)
    top_codes = codes[top].tolist() if n_hyp else [0] * n
    labels = [names[c] if h else "" for c, h in zip(top_codes, has.tolist())]
    for i in np.unique(det[~np.isfinite(sc)]).tolist():
        # a non-finite hypothesis score (rare, invalid anyway): the message reading rule one
        # by one,
        # e.g. an empty class_id scoring -inf yields to the next hypothesis
        best, label = -np.inf, ""
        for j in np.flatnonzero(det == i).tolist():
            if sc[j] > best or not label and best == -np.inf:
                best, label = sc[j], names[codes[j]]
        scores[i], labels[i] = best, label
    reasons = ["" if h else "no hypothesis in results" for h in has.tolist()]
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
        (~np.isfinite(scores) & has, "non-finite score"),
    ]
    for bad, why in checks:
        for i in np.flatnonzero(bad):
            reasons[i] = f"{reasons[i]}; {why}" if reasons[i] else why
    valid = np.array([not r for r in reasons], dtype=bool)
    return DetectionArrays(boxes=boxes, scores=scores, labels=labels, ids=list(ids),
                           roll_pitch=rpy[:, :2], valid=valid, reasons=reasons,
                           class_scores=hyps)


def _bare(msg_cls):
    """An instance of a generated message class with no field set yet (the caller sets
    every field): skips ``__init__``, which builds a default of every sub-message only
    for it to be replaced."""
    obj = msg_cls.__new__(msg_cls)
    obj._check_fields = False
    return obj


def arrays_to_detections(header, boxes: np.ndarray, labels, scores, *, ids=None,
                         class_scores: dict[str, np.ndarray] | None = None,
                         covariance_diagonal: np.ndarray | None = None):
    """Build a Detection3DArray (one result per detection, or one per finite entry of
    ``class_scores``, highest score first); ``covariance_diagonal`` (N, 6) fills the pose
    covariance diagonal (x, y, z, roll, pitch, yaw). The hypotheses of a detection share
    one PoseWithCovariance object (equal values; its pose is the box centre)."""
    from geometry_msgs.msg import PoseWithCovariance
    from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesis, ObjectHypothesisWithPose

    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    n = len(boxes)
    quat = yaw_to_quaternion(boxes[:, 6]).tolist()
    if class_scores:
        names = list(class_scores)
        S = np.column_stack([np.asarray(class_scores[c], np.float64).reshape(-1)[:n]
                             for c in names])
        order = np.argsort(-np.where(np.isfinite(S), S, -np.inf), axis=1, kind="stable")
        nfin = np.isfinite(S).sum(axis=1).tolist()
        items = [[(names[k], S[i, k]) for k in order[i, :nfin[i]].tolist()] for i in range(n)]
    else:
        items = [[(str(labels[i]), float(scores[i]))] for i in range(n)]
    cov = np.zeros((n, 36))
    if covariance_diagonal is not None:
        cov[:, ::7] = np.asarray(covariance_diagonal, np.float64).reshape(n, 6)
    out = Detection3DArray(header=header)
    for i, b in enumerate(boxes.tolist()):
        det = Detection3D(header=header, id=str(ids[i]) if ids is not None else str(i))
        p, o, s = det.bbox.center.position, det.bbox.center.orientation, det.bbox.size
        p.x, p.y, p.z = b[0], b[1], b[2]
        s.x, s.y, s.z = b[3], b[4], b[5]
        o.x, o.y, o.z, o.w = quat[i]
        pose = _bare(PoseWithCovariance)
        pose.pose, pose.covariance = det.bbox.center, cov[i]
        results = []
        for cls, sc in items[i]:
            hyp = _bare(ObjectHypothesisWithPose)
            hyp.hypothesis = ObjectHypothesis(class_id=cls, score=float(sc))
            hyp.pose = pose
            results.append(hyp)
        det.results = results
        out.detections.append(det)
    return out
