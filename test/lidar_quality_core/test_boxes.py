"""Detection3DArray <-> arrays: yaw from any quaternion, per-box rejection with reasons."""
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from lidar_quality_core.boxes import (TILT_TOLERANCE_DEG, arrays_to_detections, decoded_header,
                                      detections_to_arrays, quaternion_to_rpy, tilt_issue,
                                      yaw_to_quaternion)
from std_msgs.msg import Header
from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose


def _det(center=(1.0, 2.0, 0.5), size=(4.0, 2.0, 1.5), quat=(0.0, 0.0, 0.0, 1.0),
         hyps=(("car", 0.9),), det_id="d"):
    d = Detection3D(id=det_id)
    p, o, s = d.bbox.center.position, d.bbox.center.orientation, d.bbox.size
    p.x, p.y, p.z = center
    s.x, s.y, s.z = size
    o.x, o.y, o.z, o.w = quat
    for cls, score in hyps:
        h = ObjectHypothesisWithPose()
        h.hypothesis.class_id, h.hypothesis.score = cls, score
        d.results.append(h)
    return d


def test_roundtrip_arrays_message_arrays():
    boxes = np.array([[1, 2, 0.5, 4, 2, 1.5, 0.3], [-5, 7, 1, 0.6, 0.5, 1.7, -2.9]])
    msg = arrays_to_detections(Header(frame_id="f"), boxes, ["car", "pedestrian"], [0.8, 0.4],
                               ids=["a", "b"])
    arr = detections_to_arrays(msg)
    np.testing.assert_allclose(arr.boxes, boxes, atol=1e-12)
    assert arr.labels == ["car", "pedestrian"] and arr.ids == ["a", "b"]
    np.testing.assert_allclose(arr.scores, [0.8, 0.4])
    assert arr.valid.all() and arr.reasons == ["", ""]
    np.testing.assert_allclose(arr.roll_pitch, 0.0, atol=1e-12)


def test_top_hypothesis_and_class_distribution():
    arr = detections_to_arrays([_det(hyps=(("car", 0.2), ("truck", 0.7), ("bus", 0.1))),
                                _det(hyps=(("car", 0.6),))])
    assert arr.labels == ["truck", "car"]
    np.testing.assert_allclose(arr.scores, [0.7, 0.6])
    np.testing.assert_allclose(arr.class_scores["car"], [0.2, 0.6])
    assert np.isnan(arr.class_scores["truck"][1])


def test_covariance_and_class_scores_written():
    msg = arrays_to_detections(Header(), np.zeros((1, 7)) + [0, 0, 0, 1, 1, 1, 0], None, None,
                               class_scores={"van": np.array([0.3]), "car": np.array([0.7]),
                                             "truck": np.array([np.nan])},
                               covariance_diagonal=np.array([[1, 2, 3, 0, 0, 4.0]]))
    res = msg.detections[0].results
    assert [(r.hypothesis.class_id, r.hypothesis.score) for r in res] == [("car", 0.7), ("van", 0.3)]
    cov = np.asarray(res[0].pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(np.diag(cov), [1, 2, 3, 0, 0, 4])


def test_invalid_boxes_rejected_with_reason():
    dets = [_det(),
            _det(size=(4.0, 0.0, 1.5)),
            _det(center=(math.nan, 0, 0)),
            _det(quat=(0, 0, 0, 0)),
            _det(hyps=()),
            _det(size=(math.inf, 1, 1)),
            _det(hyps=(("car", math.nan),)),
            _det(quat=(0, 0, math.nan, 1))]
    arr = detections_to_arrays(Detection3DArray(detections=dets))
    assert arr.valid.tolist() == [True] + [False] * 7
    assert arr.reasons[1] == "size <= 0"
    assert arr.reasons[2] == "non-finite centre"
    assert arr.reasons[3] == "zero quaternion"
    assert arr.reasons[4] == "no hypothesis in results"
    assert arr.reasons[5] == "non-finite size"
    assert arr.reasons[6] == "non-finite score"
    assert arr.reasons[7] == "non-finite orientation"
    assert len(arr) == 8  # rejected rows stay, so outputs can be matched to inputs


def test_empty():
    arr = detections_to_arrays(Detection3DArray())
    assert arr.boxes.shape == (0, 7) and len(arr) == 0 and arr.valid.shape == (0,)


def _quat_from_rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = (math.cos(r / 2), math.sin(r / 2), math.cos(p / 2),
                              math.sin(p / 2), math.cos(y / 2), math.sin(y / 2))
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


angle = st.floats(-math.pi + 1e-3, math.pi - 1e-3)


@settings(max_examples=200, deadline=None)
@given(r=st.floats(-1.4, 1.4), p=st.floats(-1.4, 1.4), y=angle,
       scale=st.floats(0.1, 10.0), flip=st.booleans())
def test_yaw_from_any_quaternion(r, p, y, scale, flip):
    q = np.array(_quat_from_rpy(r, p, y)) * scale * (-1 if flip else 1)  # q and -q: same rotation
    rpy = quaternion_to_rpy(q[None])[0]
    np.testing.assert_allclose(rpy, [r, p, y], atol=1e-7)
    arr = detections_to_arrays([_det(quat=tuple(q))])
    assert math.isclose(arr.boxes[0, 6], y, abs_tol=1e-7)
    np.testing.assert_allclose(arr.roll_pitch[0], [r, p], atol=1e-7)


def test_tilted_boxes_are_kept_and_reported():
    """Roll / pitch were dropped without a word; the box stays (valid, yaw kept) and
    ``tilt_issue`` words the warning, ignoring invalid boxes and float32 rounding."""
    deg = math.radians
    yaw32 = tuple(float(v) for v in np.float32(yaw_to_quaternion(np.array([2.0]))[0]))
    arr = detections_to_arrays([
        _det(quat=_quat_from_rpy(deg(30), 0.0, 0.4), det_id="rolled"),
        _det(quat=_quat_from_rpy(0.0, deg(-2.0), -1.0), det_id="pitched"),
        _det(quat=_quat_from_rpy(deg(0.9), deg(-0.9), 3.0), det_id="within tolerance"),
        _det(quat=yaw32, det_id="float32 upright"),
        _det(quat=_quat_from_rpy(deg(45), 0.0, 0.0), size=(0.0, 1.0, 1.0), det_id="invalid"),
    ])
    assert arr.valid.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(arr.boxes[:4, 6], [0.4, -1.0, 3.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(arr.tilt_deg(), [30.0, 2.0, 0.9, 0.0, 45.0], atol=1e-6)
    assert TILT_TOLERANCE_DEG == 1.0
    assert tilt_issue(arr) == ("2 of 5 boxes have roll/pitch up to 30.0 deg: only yaw is "
                               "used (boxes are read as upright)")
    assert tilt_issue(arr, "proposals", tolerance_deg=0.5).startswith(
        "3 of 5 proposals have roll/pitch up to 30.0 deg")
    upright = detections_to_arrays(arrays_to_detections(
        Header(), np.array([[0, 0, 0, 1, 1, 1, 2.5]]), ["car"], [0.5]))
    assert tilt_issue(upright) is None and tilt_issue(detections_to_arrays([])) is None


def test_tilt_issue_at_the_tolerance_counts_in_degrees():
    # tilt_issue checks the radians first (just under the tolerance), then counts in
    # degrees: a box a rounding step above the tolerance is reported, one at it is not
    from dataclasses import replace
    arr = detections_to_arrays(arrays_to_detections(
        Header(), np.zeros((4, 7)) + [0, 0, 0, 1, 1, 1, 0], ["car"] * 4, [0.5] * 4))
    at = math.radians(TILT_TOLERANCE_DEG)
    rp = np.array([[at, 0.0], [0.0, -at], [np.nan, 0.0], [0.0, 0.0]])
    assert tilt_issue(replace(arr, roll_pitch=rp)) is None
    up = np.nextafter(np.degrees(at), np.inf)
    rp[1, 1] = -np.radians(np.nextafter(up, np.inf))
    assert np.degrees(abs(rp[1, 1])) > TILT_TOLERANCE_DEG
    assert tilt_issue(replace(arr, roll_pitch=rp)).startswith("1 of 4 boxes")
    # strided (a view of roll, pitch, yaw) and invalid boxes
    rpy = np.column_stack([rp, np.zeros(4)])
    assert tilt_issue(replace(arr, roll_pitch=rpy[:, :2])).startswith("1 of 4 boxes")
    assert tilt_issue(replace(arr, roll_pitch=rp,
                              valid=np.array([True, False, True, True]))) is None


@given(y=angle)
def test_yaw_quaternion_inverse(y):
    assert math.isclose(quaternion_to_rpy(yaw_to_quaternion(np.array([y])))[0, 2], y, abs_tol=1e-9)


def _reference_top(hyps):
    """The message reading rule, hypothesis by hypothesis."""
    best, label = -math.inf, ""
    for cls, sc in hyps:
        if sc > best or not label and best == -math.inf:
            best, label = sc, cls
    return label, (best if hyps else math.nan)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(st.tuples(st.sampled_from(["", "car", "truck", "ped"]),
                                   st.sampled_from([math.nan, -math.inf, math.inf, 0.0, 0.2,
                                                    0.5, 0.5, 0.9, -1.0])),
                         max_size=5), max_size=6))
def test_arrays_from_fields_top_hypothesis_and_columns(per_det):
    from lidar_quality_core.boxes import arrays_from_fields
    raw = np.tile([0, 0, 0, 1, 1, 1, 0, 0, 0, 1.0], (len(per_det), 1))
    flat = [(i, c, s) for i, hs in enumerate(per_det) for c, s in hs]
    arr = arrays_from_fields(raw, [str(i) for i in range(len(per_det))],
                             [f[0] for f in flat], [f[1] for f in flat], [f[2] for f in flat])
    for i, hs in enumerate(per_det):
        label, score = _reference_top(hs)
        assert arr.labels[i] == label
        np.testing.assert_array_equal(arr.scores[i], score)
        assert (arr.reasons[i] == "no hypothesis in results") == (not hs)
        for c in {c for c, _ in hs}:
            np.testing.assert_array_equal(arr.class_scores[c][i], [s for k, s in hs if k == c][-1])
    assert list(arr.class_scores) == list(dict.fromkeys(f[1] for f in flat))


def test_decoded_header_is_the_header_rclpy_builds():
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message

    h = decoded_header(-3, 999_999_999, "lidar_top")
    want = Header(frame_id="lidar_top", stamp=Time(sec=-3, nanosec=999_999_999))
    assert h == want and repr(h) == repr(want)
    assert (h.stamp.sec, h.stamp.nanosec, h.frame_id) == (-3, 999_999_999, "lidar_top")
    assert serialize_message(h) == serialize_message(want)
    assert deserialize_message(serialize_message(h), Header) == want
    h.frame_id = "map"  # a decoded header stays an ordinary message
    assert h.frame_id == "map" and h != want
