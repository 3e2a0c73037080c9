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

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, types

from .kernel_types import array_in, array_out

BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw")
#: |roll| or |pitch| above this [deg] is reported: float32 quaternions of upright boxes
#: stay far below it, a detector that really tilts its boxes far above.
TILT_TOLERANCE_DEG = 1.0


@njit(types.Tuple((array_out(types.float64, 2), array_out(types.float64, 2),
                    array_out(types.float64)))(array_in(types.float64, 2, "A")),
      cache=True, nogil=True, error_model="numpy")
def rpy_terms(q):
    """Arguments of ``quaternion_to_rpy``'s three functions, in one pass: the normalised
    quaternion's ``(y, x)`` of roll and yaw (rows 0, 1) and the clipped sine of pitch; the
    same operations in the same order as numpy's (``np.linalg.norm``: ((x² + y²) + z²)
    + w²), so the angles are bit for bit what the numpy expressions gave."""
    n = q.shape[0]
    num, den, sine = np.empty((2, n)), np.empty((2, n)), np.empty(n)
    for i in range(n):
        norm = np.sqrt(((q[i, 0] * q[i, 0] + q[i, 1] * q[i, 1]) + q[i, 2] * q[i, 2])
                       + q[i, 3] * q[i, 3])
        x, y, z, w = q[i, 0] / norm, q[i, 1] / norm, q[i, 2] / norm, q[i, 3] / norm
        num[0, i], den[0, i] = 2 * (w * x + y * z), 1 - 2 * (x * x + y * y)
        num[1, i], den[1, i] = 2 * (w * z + x * y), 1 - 2 * (y * y + z * z)
        v = 2 * (w * y - z * x)
        sine[i] = 1.0 if v > 1.0 else (-1.0 if v < -1.0 else v)  # NaN stays NaN
    return num, den, sine


def quaternion_to_rpy(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions ``x, y, z, w`` (any norm > 0) -> (N, 3) roll, pitch, yaw (ZYX)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    return rpy_angles(*rpy_terms(q))


def rpy_angles(num: np.ndarray, den: np.ndarray, sine: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw from :func:`rpy_terms`' arguments."""
    out = np.empty((len(sine), 3))
    # numpy's arctan2 / arcsin (one call each): the angles stay those of its libm
    roll_yaw = np.arctan2(num, den)
    out[:, 0], out[:, 1], out[:, 2] = roll_yaw[0], np.arcsin(sine), roll_yaw[1]
    return out


def yaw_to_quaternion(yaw: np.ndarray) -> np.ndarray:
    """Yaw angles (N,) -> (N, 4) quaternions ``x, y, z, w`` of a rotation about +z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64).reshape(-1)
    out = np.zeros((len(half), 4))
    out[:, 2], out[:, 3] = np.sin(half), np.cos(half)
    return out


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


@njit(types.boolean(array_in(types.float64, 2, "A"), array_in(types.boolean, 1, "A"),
                    types.float64), cache=True, nogil=True)
def _maybe_tilted(roll_pitch, valid, limit_rad):
    # a valid box with |roll| or |pitch| above the limit (NaN is not): the usual frame
    # has none, and this one call is all it costs (the degrees below are ~6 numpy calls)
    for i in range(roll_pitch.shape[0]):
        if valid[i] and (abs(roll_pitch[i, 0]) > limit_rad or abs(roll_pitch[i, 1]) > limit_rad):
            return True
    return False


def tilt_issue(arrays: DetectionArrays, what: str = "boxes",
               tolerance_deg: float = TILT_TOLERANCE_DEG) -> str | None:
    """``"3 of 12 boxes have roll/pitch up to 30.0 deg: only yaw is used"`` when valid
    boxes of ``arrays`` are tilted by more than ``tolerance_deg``, else None."""
    n = len(arrays)
    # just under the tolerance: the count below decides, in degrees
    if not n or not _maybe_tilted(np.asarray(arrays.roll_pitch, np.float64).reshape(n, 2),
                                  np.asarray(arrays.valid, bool),
                                  math.radians(tolerance_deg) * (1.0 - 1e-9)):
        return None
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


#: ``hypothesis_table``'s flags, in the order the reasons are listed
_REASONS = ((1, "no hypothesis in results"), (2, "non-finite centre"), (4, "non-finite size"),
            (8, "size <= 0"), (16, "non-finite orientation"), (32, "zero quaternion"),
            (64, "non-finite score"))


@njit("Tuple((float64[::1], int64[::1], float64[:, ::1], int64[::1]))(float64[:, ::1], "
      "int64[::1], int64[::1], float64[::1], boolean[::1])", cache=True, nogil=True)
def hypothesis_table(raw, det, codes, sc, name_empty):
    """Per detection: score and class code (-1: none) of its top hypothesis, the class
    score table (classes, N) and the flags of ``_REASONS``; one pass in message order."""
    n, n_hyp, n_names = raw.shape[0], det.shape[0], name_empty.shape[0]
    cls = np.full((n_names, n), np.nan)
    best = np.full(n, -1, np.int64)         # index of the top hypothesis so far
    nonfinite = np.zeros(n, np.bool_)
    # the rule for a detection with a non-finite score, as one reads the message: a
    # hypothesis wins if it scores higher, or while the label is still empty and the best
    # is -inf (e.g. an empty class_id scoring -inf yields to the next hypothesis)
    nf_score = np.full(n, -np.inf)
    nf_code = np.full(n, -1, np.int64)
    nf_empty = np.ones(n, np.bool_)
    for j in range(n_hyp):
        i, c, v = det[j], codes[j], sc[j]
        cls[c, i] = v                       # a class given twice: the last one
        if best[i] < 0 or v > sc[best[i]]:  # strictly higher; NaN never wins, a NaN first stays
            best[i] = j
        if not np.isfinite(v):
            nonfinite[i] = True
        if v > nf_score[i] or (nf_empty[i] and nf_score[i] == -np.inf):
            nf_score[i], nf_code[i], nf_empty[i] = v, c, name_empty[c]
    scores = np.full(n, np.nan)
    top = np.full(n, -1, np.int64)
    flags = np.zeros(n, np.int64)
    for i in range(n):
        if best[i] < 0:
            flags[i] |= 1
        elif nonfinite[i]:
            scores[i], top[i] = nf_score[i], nf_code[i]
        else:
            scores[i], top[i] = sc[best[i]], codes[best[i]]
        centre, size, quat = True, True, True
        for k in range(3):
            centre &= np.isfinite(raw[i, k])
            size &= np.isfinite(raw[i, 3 + k])
        for k in range(4):
            quat &= np.isfinite(raw[i, 6 + k])
        if not centre:
            flags[i] |= 2
        if not size:
            flags[i] |= 4
        elif raw[i, 3] <= 0 or raw[i, 4] <= 0 or raw[i, 5] <= 0:
            flags[i] |= 8
        if not quat:
            flags[i] |= 16
        elif centre and size:
            q2 = raw[i, 6] ** 2 + raw[i, 7] ** 2 + raw[i, 8] ** 2 + raw[i, 9] ** 2
            if np.sqrt(q2) < 1e-9:
                flags[i] |= 32
        if best[i] >= 0 and not np.isfinite(scores[i]):
            flags[i] |= 64
    return scores, top, cls, flags


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
    name_empty = np.array([not c for c in names], dtype=np.bool_)
    scores, top, cls, flags = hypothesis_table(*(np.require(a, t, "CW") for a, t in (
        (raw, np.float64), (det, np.int64), (codes, np.int64), (sc, np.float64),
        (name_empty, np.bool_))))
    rpy = quaternion_to_rpy(raw[:, 6:10]) if n else np.zeros((0, 3))
    return arrays_from_table(raw, ids, names, scores, top, cls, flags, rpy)


def arrays_from_table(raw: np.ndarray, ids: list[str], names: list[str], scores, top, cls,
                      flags, rpy) -> DetectionArrays:
    """The DetectionArrays of :func:`arrays_from_fields` from its compiled parts:
    ``hypothesis_table``'s ``(scores, top, cls, flags)`` and the (N, 3) roll, pitch, yaw
    ``rpy`` (``detection_cdr`` computes both in its decoding pass)."""
    n = len(raw)
    hyps = {name: cls[k] for k, name in enumerate(names)}
    labels = [names[c] if c >= 0 else "" for c in top.tolist()]
    reasons = [""] * n
    # the usual message has no unusable box: ~10 calls spared (count_nonzero: a C call;
    # ndarray.any goes through a ufunc reduction, several times dearer once cold)
    if np.count_nonzero(flags):
        for i, f in zip(np.flatnonzero(flags).tolist(), flags[flags != 0].tolist()):
            reasons[i] = "; ".join(why for bit, why in _REASONS if f & bit)
    boxes = np.concatenate([raw[:, :6], rpy[:, 2:3]], axis=1)
    valid = flags == 0
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


_HEADER_TYPES = None  # (Time, Header), once decoded_header has imported them


def decoded_header(sec: int, nanosec: int, frame_id: str):
    """The std_msgs/Header of a decoded message (the CDR decoders' one place): built
    field by field like :func:`_bare`'s messages (``Header(frame_id=...)`` and setting
    its stamp were ~15 Python calls, paid for every message a node takes)."""
    global _HEADER_TYPES
    if _HEADER_TYPES is None:  # imported on first use, as the other message types here
        from builtin_interfaces.msg import Time
        from std_msgs.msg import Header

        _HEADER_TYPES = Time, Header
    Time, Header = _HEADER_TYPES
    stamp = _bare(Time)
    stamp._sec, stamp._nanosec = sec, nanosec
    h = _bare(Header)
    h._stamp, h._frame_id = stamp, frame_id
    return h


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
