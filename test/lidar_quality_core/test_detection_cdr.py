"""detection_cdr: decoding equals rclpy deserialization + detections_to_arrays; encoding is
what rclpy serializes for the same message (subset, new scores); bad bytes refused."""
import math

import numpy as np
import pytest
from lidar_quality_core.boxes import detections_to_arrays, tilt_issue
from lidar_quality_core.detection_cdr import (CdrError, decode_detection_array,
                                              encode_detection_array, rescaled_scores)
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header
from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose


def random_array(seed, n=7, same_headers=False):
    """Detections with varied string lengths (every alignment), 0..4 hypotheses, random
    poses and covariances, a NaN box and non-ASCII ids. ``same_headers``: every detection
    has the array's header (as detectors publish them), else each its own."""
    rng = np.random.default_rng(seed)
    h = Header(frame_id="f" * int(rng.integers(0, 9)))
    h.stamp.sec, h.stamp.nanosec = int(rng.integers(-5, 2**31 - 1)), int(rng.integers(0, 10**9))
    dets = []
    for i in range(n):
        d = Detection3D(id="é" * int(rng.integers(0, 5)) + "x" * int(rng.integers(0, 7)))
        d.header.frame_id = "g" * int(rng.integers(0, 6))
        d.header.stamp.sec = i
        if same_headers:
            d.header = h
        c, s = d.bbox.center, d.bbox.size
        c.position.x, c.position.y, c.position.z = rng.normal(size=3).tolist()
        q = rng.normal(size=4)
        c.orientation.x, c.orientation.y, c.orientation.z, c.orientation.w = q.tolist()
        s.x, s.y, s.z = rng.uniform(0.5, 4, 3).tolist()
        for _ in range(int(rng.integers(0, 5))):
            r = ObjectHypothesisWithPose()
            r.hypothesis.class_id = "c" * int(rng.integers(1, 10))
            r.hypothesis.score = float(rng.uniform(-0.2, 1))
            p = r.pose.pose
            p.position.x, p.position.y, p.position.z = rng.normal(size=3).tolist()
            p.orientation.w = float(rng.normal())
            r.pose.covariance = rng.normal(size=36)
            d.results.append(r)
        dets.append(d)
    dets[n // 2].bbox.center.position.y = math.nan
    return Detection3DArray(header=h, detections=dets)


def assert_arrays_equal(a, b):
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.roll_pitch, b.roll_pitch)
    assert (a.labels, a.ids, a.reasons) == (b.labels, b.ids, b.reasons)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.class_scores.keys() == b.class_scores.keys()
    for k in a.class_scores:
        np.testing.assert_array_equal(a.class_scores[k], b.class_scores[k])


@pytest.mark.parametrize("seed", range(12))
def test_decode_equals_rclpy(seed):
    msg = random_array(seed)
    dec = decode_detection_array(serialize_message(msg))
    assert dec.header == msg.header
    assert_arrays_equal(dec.arrays, detections_to_arrays(msg))
    # random orientations: the tilt warning, worded from the same arrays
    assert tilt_issue(dec.arrays) == tilt_issue(detections_to_arrays(msg)) is not None
    assert dec.hyp_score.tolist() == [r.hypothesis.score for d in msg.detections
                                      for r in d.results]


@pytest.mark.parametrize("seed", range(12))
def test_encode_subset_with_new_scores_equals_rclpy(seed):
    msg = random_array(seed)
    dec = decode_detection_array(serialize_message(msg))
    rng = np.random.default_rng(seed)
    rows = rng.permutation(len(msg.detections))[:4]
    new = rng.uniform(size=len(dec.hyp_score))
    out = deserialize_message(encode_detection_array(dec, rows, new), Detection3DArray)
    want = deserialize_message(serialize_message(msg), Detection3DArray)
    want.detections = [want.detections[i] for i in rows]
    flat = iter(np.split(new, dec.hyp_offsets[1:-1]))
    per_det = list(flat)
    for d, i in zip(want.detections, rows):
        for r, v in zip(d.results, per_det[i]):
            r.hypothesis.score = float(v)
    assert out.header == want.header
    assert len(out.detections) == len(rows)
    for a, b in zip(out.detections, want.detections):  # NaN != NaN: compare field-wise
        assert a.header == b.header and a.id == b.id and len(a.results) == len(b.results)
        np.testing.assert_array_equal(
            [a.bbox.center.position.x, a.bbox.center.position.y, a.bbox.size.z],
            [b.bbox.center.position.x, b.bbox.center.position.y, b.bbox.size.z])
        assert a.bbox.center.orientation == b.bbox.center.orientation
        assert a.results == b.results
    # all rows, scores kept: byte-identical to rclpy up to padding bytes
    full = encode_detection_array(dec, np.arange(len(dec)))
    assert len(full) == len(serialize_message(msg))
    again = decode_detection_array(full)
    assert_arrays_equal(again.arrays, dec.arrays)


def test_encode_refuses_rows_and_scores_it_cannot_write():
    """The compiled writer reads where the rows point: a row outside the array or a
    score vector of another length is an error, not a read past the message."""
    dec = decode_detection_array(serialize_message(random_array(3)))
    n, h = len(dec), len(dec.hyp_score)
    for rows in ([n], [-1], [0, n + 5]):
        with pytest.raises(IndexError):
            encode_detection_array(dec, rows)
    with pytest.raises(ValueError):
        encode_detection_array(dec, [0], np.zeros(h + 1))
    assert encode_detection_array(dec, [n - 1, 0]) == encode_detection_array(
        dec, np.array([n - 1, 0], np.int32))


def test_empty_array():
    dec = decode_detection_array(serialize_message(Detection3DArray()))
    assert len(dec) == 0 and dec.arrays.boxes.shape == (0, 7)
    out = deserialize_message(encode_detection_array(dec, []), Detection3DArray)
    assert out == Detection3DArray()


def test_bad_bytes_refused():
    good = serialize_message(random_array(0))
    for bad, match in [(b"", "encapsulation"), (b"\x00\x07\x00\x00" + good[4:], "encapsulation"),
                       (good[:len(good) // 2], "truncated|bad string"),
                       (good[:12] + b"\xff\xff\xff\x7f" + good[16:], "bad string")]:
        with pytest.raises(CdrError, match=match):
            decode_detection_array(bad)


def test_rescaled_scores():
    s = np.array([0.6, 0.2, 0.0, -1.0, 0.3, math.nan, 0.5, 0.5])
    det = np.array([0, 0, 1, 1, 2, 3, 4, 4])
    out = rescaled_scores(s, det, np.array([0.3, 0.8, math.nan, 0.4, 0.9]))
    np.testing.assert_allclose(out[:2], [0.3, 0.1])       # ratio kept, top = confidence
    assert out[2:4].tolist() == [0.8, -1.0]               # top 0: set, others unchanged
    assert math.isnan(out[4])                             # NaN confidence
    assert out[5] == 0.4                                  # no finite score: first set
    assert out[6:].tolist() == [0.9, 0.9]                 # tied tops both = confidence


@pytest.mark.parametrize("n,frame_id", [(0, "lidar"), (1, ""), (9, "lidar_top"), (40, "ab")])
def test_encode_detections_is_the_message_arrays_to_detections_builds(n, frame_id):
    from lidar_quality_core.boxes import arrays_to_detections
    from lidar_quality_core.detection_cdr import encode_detections

    rng = np.random.default_rng(n)
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = 123, 456789
    boxes = rng.normal(size=(n, 7))
    boxes[:, 3:6] = np.abs(boxes[:, 3:6]) + 0.1
    names = ("car", "truck", "pedestrian", "cyclist")
    S = rng.random((n, 4))
    S[rng.random((n, 4)) < 0.2] = np.nan      # absent hypotheses
    S[: min(n, 3), 1] = S[: min(n, 3), 0]     # ties keep the column order
    if n >= 9:
        S[3:6, 2], S[6:8, 3] = np.inf, -np.inf    # not finite: no hypothesis, as NaN
        S[8, :] = [0.0, -0.0, 0.0, -0.0]          # signed zeros tie: column order
    ids = [f"{k % 3}:{'é' * (k % 4)}{k}" for k in range(n)]
    for cov in (None, rng.random((n, 6))):
        ref = arrays_to_detections(h, boxes, None, None, ids=ids, covariance_diagonal=cov,
                                   class_scores={c: S[:, k] for k, c in enumerate(names)})
        data = encode_detections(h, boxes, names, S, ids=ids, covariance_diagonal=cov)
        assert len(data) == len(serialize_message(ref))
        got = deserialize_message(data, Detection3DArray)
        assert got.header == h and len(got.detections) == n
        for x, y in zip(got.detections, ref.detections):
            assert (x.header, x.id, x.bbox) == (y.header, y.id, y.bbox)
            assert [(r.hypothesis.class_id, r.hypothesis.score) for r in x.results] == [
                (r.hypothesis.class_id, r.hypothesis.score) for r in y.results]
            for r, q in zip(x.results, y.results):
                assert r.pose.pose == q.pose.pose
                np.testing.assert_array_equal(r.pose.covariance, q.pose.covariance)
        # and our own decoder reads it back
        dec = decode_detection_array(data)
        np.testing.assert_allclose(dec.arrays.boxes[:, :6], boxes[:, :6])
        assert dec.arrays.ids == ids


def test_class_names_sharing_prefixes_and_lengths():
    names = ["pedestrian_a", "pedestrian_b", "car", "bus", "pedestrian_a", "ü", "car",
             "x" * 40, "x" * 39 + "y"]
    msg = Detection3DArray()
    for k, name in enumerate(names):
        d = Detection3D(id=str(k))
        d.bbox.size.x = d.bbox.size.y = d.bbox.size.z = 1.0
        d.bbox.center.orientation.w = 1.0
        for j, other in enumerate((name, names[(k + 3) % len(names)])):
            r = ObjectHypothesisWithPose()
            r.hypothesis.class_id, r.hypothesis.score = other, 0.9 - 0.1 * j
            d.results.append(r)
        msg.detections.append(d)
    dec = decode_detection_array(serialize_message(msg))
    assert_arrays_equal(dec.arrays, detections_to_arrays(msg))
    assert dec.arrays.labels == names


def _step_by_step(raw, p, n):
    """A ``_decode`` that declines every message: the decoder then takes its step-by-step
    path (``_walk``, ``_fields``, ``boxes.arrays_from_fields``)."""
    return (False,) + (None,) * 19


def _decode_both(data, monkeypatch):
    """(result or CdrError text) of the decoder with its compiled pass, and with the
    Python loop walking the layout and ``_class_codes`` grouping the class names."""
    from lidar_quality_core import detection_cdr

    out = []
    compiled = detection_cdr._walk
    for walk in (compiled, lambda raw, p, n: (0,) + (None,) * 9):
        monkeypatch.setattr(detection_cdr, "_walk", walk)
        if walk is not compiled:
            monkeypatch.setattr(detection_cdr, "_decode", _step_by_step)
        try:
            out.append(decode_detection_array(data))
        except CdrError as exc:
            out.append(str(exc))
    return out


@pytest.mark.parametrize("same_headers", [True, False])
@pytest.mark.parametrize("seed", range(8))
def test_compiled_walk_finds_what_the_loop_finds(seed, same_headers, monkeypatch):
    from lidar_quality_core.detection_cdr import _walk, open_array

    msg = random_array(seed, n=40, same_headers=same_headers)
    data = serialize_message(msg)
    buf, _, _, n, p = open_array(data, "Detection3DArray", "detections", 100)
    assert _walk(np.frombuffer(buf, np.uint8), p, n)[0] == 1  # valid bytes: the fast path
    fast, loop = _decode_both(data, monkeypatch)
    assert_arrays_equal(fast.arrays, detections_to_arrays(msg))
    assert_arrays_equal(fast.arrays, loop.arrays)
    for name in ("det_spans", "bbox_at", "id_at", "hyp_offsets", "hyp_det", "hyp_class_at",
                 "hyp_score_at", "hyp_score"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(loop, name))
    assert encode_detection_array(fast, np.arange(n)) == encode_detection_array(loop, np.arange(n))


@pytest.mark.parametrize("seed", range(6))
def test_one_compiled_pass_decodes_as_the_steps_do(seed, monkeypatch):
    """``_decode`` (walk, fields, ids, hypothesis rules and angle terms in one compiled
    call) gives what the step-by-step path gives: every array and offset, with empty
    class names, NaN / inf scores and boxes, zero quaternions and detections without
    hypotheses among them."""
    from lidar_quality_core import detection_cdr

    msg = random_array(seed, n=60, same_headers=seed % 2 == 0)
    rng = np.random.default_rng(seed)
    for d in msg.detections[::5]:
        d.results = d.results[:int(rng.integers(0, 2))]
    for d in msg.detections[1::7]:
        if d.results:
            d.results[0].hypothesis.class_id = ""
            d.results[-1].hypothesis.score = float(rng.choice([np.nan, np.inf, -np.inf]))
    msg.detections[2].bbox.center.orientation.x = msg.detections[2].bbox.center.orientation.y = 0.0
    msg.detections[2].bbox.center.orientation.z = msg.detections[2].bbox.center.orientation.w = 0.0
    msg.detections[3].bbox.size.x = np.nan
    msg.detections[4].bbox.center.position.y = np.inf
    data = serialize_message(msg)
    buf, _, _, n, p = detection_cdr.open_array(data, "Detection3DArray", "detections", 100)
    assert detection_cdr._decode(np.frombuffer(buf, np.uint8), p, n)[0]  # taken in one pass
    fused = decode_detection_array(data)
    monkeypatch.setattr(detection_cdr, "_decode", _step_by_step)
    steps = decode_detection_array(data)
    assert_arrays_equal(fused.arrays, steps.arrays)
    assert_arrays_equal(fused.arrays, detections_to_arrays(msg))
    np.testing.assert_array_equal(fused.arrays.roll_pitch, steps.arrays.roll_pitch)
    for name in ("det_spans", "bbox_at", "id_at", "hyp_offsets", "hyp_det", "hyp_class_at",
                 "hyp_score_at", "hyp_score"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(steps, name))


def test_many_class_names_are_grouped_alike(monkeypatch):
    from lidar_quality_core import detection_cdr

    msg = random_array(3, n=30)
    k = 0
    for d in msg.detections:  # more distinct names than the compiled grouping keeps
        for r in d.results:
            r.hypothesis.class_id = f"class_{k % (detection_cdr._MAX_CLASSES + 20)}"
            k += 1
    assert k > detection_cdr._MAX_CLASSES
    data = serialize_message(msg)
    buf, _, _, n, p = detection_cdr.open_array(data, "Detection3DArray", "detections", 100)
    assert detection_cdr._walk(np.frombuffer(buf, np.uint8), p, n)[0] == 2
    fast, loop = _decode_both(data, monkeypatch)
    assert_arrays_equal(fast.arrays, detections_to_arrays(msg))
    assert_arrays_equal(fast.arrays, loop.arrays)


@pytest.mark.parametrize("seed", range(6))
def test_damaged_bytes_decode_alike_on_both_walks(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    good = bytearray(serialize_message(random_array(seed, n=30, same_headers=seed % 2 == 0)))
    for _ in range(60):
        bad = bytearray(good)
        for at in rng.integers(4, len(bad), size=int(rng.integers(1, 4))):
            bad[at] = int(rng.integers(0, 256))
        if rng.uniform() < 0.3:
            bad = bad[:int(rng.integers(20, len(bad)))]
        fast, loop = _decode_both(bytes(bad), monkeypatch)
        if isinstance(loop, str):
            assert fast == loop
        else:
            assert_arrays_equal(fast.arrays, loop.arrays)
            np.testing.assert_array_equal(fast.det_spans, loop.det_spans)


def _opened(data, monkeypatch=None):
    """``open_array``'s result (header as a tuple) or its error text; with
    ``monkeypatch``: by the Python path alone (the compiled opening declines)."""
    from lidar_quality_core import detection_cdr

    if monkeypatch is not None:
        monkeypatch.setattr(detection_cdr, "_opening", lambda raw: (0,) * 6)
    try:
        buf, words, h, n, p = detection_cdr.open_array(data, "Detection3DArray",
                                                       "detections", 100)
        return (h.stamp.sec, h.stamp.nanosec, h.frame_id, n, p, bytes(words))
    except CdrError as exc:
        return str(exc)
    finally:
        if monkeypatch is not None:
            monkeypatch.undo()


@pytest.mark.parametrize("seed", range(4))
def test_compiled_opening_reads_what_the_python_path_reads(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    msg = random_array(seed, n=3)
    msg.header.frame_id = ["", "lidar", "é" * 3, "x" * 11][seed]
    msg.header.stamp.sec = [-(2**31), -1, 0, 2**31 - 1][seed]
    good = serialize_message(msg)
    cases = [good, b"", good[:3], good[:15], good[:16], good[:20], b"\x00\x07" + good[2:]]
    frame_id_at = 16
    if len(msg.header.frame_id):
        not_utf8 = bytearray(good)
        not_utf8[frame_id_at] = 0xFF
        cases.append(bytes(not_utf8))
    for _ in range(40):
        bad = bytearray(good)
        for at in rng.integers(4, min(len(bad), 40), size=int(rng.integers(1, 3))):
            bad[at] = int(rng.integers(0, 256))
        cases.append(bytes(bad[:int(rng.integers(4, len(bad) + 1))]))
    for data in cases:
        assert _opened(data) == _opened(data, monkeypatch)
    assert isinstance(_opened(good), tuple)


def _with_ids(ids):
    return Detection3DArray(detections=[Detection3D(id=i) for i in ids])


def test_ids_with_a_nul_inside_are_read_whole():
    """The ids are read at once, split at NULs; an id that holds a NUL itself (CDR allows
    it) is read string by string, whole."""
    data = bytearray(serialize_message(_with_ids(["aXb", "", "cc"])))
    data[data.index(b"aXb") + 1] = 0
    assert decode_detection_array(bytes(data)).arrays.ids == ["a\0b", "", "cc"]
    assert decode_detection_array(serialize_message(_with_ids(["", "", "é"]))).arrays.ids == [
        "", "", "é"]


def test_an_id_that_is_not_utf8_is_refused():
    data = bytearray(serialize_message(_with_ids(["ok", "aXb"])))
    data[data.index(b"aXb") + 1] = 0xFF
    with pytest.raises(CdrError, match="an id is not UTF-8"):
        decode_detection_array(bytes(data))
