"""autoware_cdr: DetectedObjects decoded from their bytes as the message path reads them,
and re-scored output bytes equal to the message path's, for every shape and class layout."""
import copy

import numpy as np
import pytest
from autoware_perception_msgs.msg import DetectedObjects
from lidar_quality_core.autoware_cdr import decode_detected_objects, encode_detected_objects
from lidar_quality_core.autoware_objects import (kept_objects, objects_to_arrays,
                                                 parse_class_map, score_objects)
from lidar_quality_core.detection_cdr import CdrError
from rclpy.serialization import deserialize_message, serialize_message
from autoware_scenes import hand_built_scene as _scene


def _scene_with_extremes():
    msg = _scene()
    msg.objects[1].classification = []          # no class at all
    msg.objects[2].shape.footprint.points = msg.objects[2].shape.footprint.points * 3
    msg.objects[0].kinematics.pose_with_covariance.covariance = np.arange(36.0)
    msg.objects[0].kinematics.has_twist = True
    msg.objects[0].kinematics.twist_with_covariance.twist.linear.x = 3.5
    msg.header.frame_id = "base_link_with_a_longer_name"
    return msg


def _same(a, b):
    np.testing.assert_array_equal(a.boxes, b.boxes)
    assert a.labels == b.labels and a.ids == b.ids and a.reasons == b.reasons
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.class_scores.keys() == b.class_scores.keys()
    for k in a.class_scores:
        np.testing.assert_array_equal(a.class_scores[k], b.class_scores[k])


@pytest.mark.parametrize("class_map", [None, "CAR:car BUS:truck"])
def test_decode_equals_the_message_path(class_map):
    cm = parse_class_map(class_map) if class_map else None
    msg = _scene_with_extremes()
    raw = serialize_message(msg)
    dec = decode_detected_objects(raw, cm)
    _same(dec.arrays, objects_to_arrays(deserialize_message(raw, DetectedObjects), cm))
    assert dec.header == msg.header and len(dec) == 5
    np.testing.assert_allclose(dec.existence, [o.existence_probability for o in msg.objects],
                               rtol=1e-7)


def test_empty_array():
    dec = decode_detected_objects(serialize_message(DetectedObjects()))
    assert len(dec) == 0 and len(dec.arrays) == 0
    out, n = encode_detected_objects(dec, [], [])
    assert n == 0 and deserialize_message(out, DetectedObjects).objects == []


@pytest.mark.parametrize("fallback", [None, 0.25])
def test_encoded_output_equals_the_message_path(fallback):
    msg = _scene_with_extremes()
    raw = serialize_message(msg)
    conf = np.array([0.9, np.nan, 0.3, 0.6, np.nan])
    rows = np.array([0, 2, 3, 4])  # a threshold dropped object 1
    out, n = encode_detected_objects(decode_detected_objects(raw), rows, conf,
                                     fallback=fallback)
    want = deserialize_message(raw, DetectedObjects)
    assert score_objects(want, conf, fallback=fallback) == n == 2
    want = kept_objects(want, np.isin(np.arange(5), rows))
    got = deserialize_message(out, DetectedObjects)
    # float32 fields: compared as they travel
    assert got == deserialize_message(serialize_message(want), DetectedObjects)
    assert len(out) == len(serialize_message(want))


def test_truncated_or_foreign_bytes_are_refused():
    raw = serialize_message(_scene_with_extremes())
    for cut in (3, 10, 40, len(raw) // 2, len(raw) - 1):
        with pytest.raises(CdrError):
            decode_detected_objects(raw[:cut])
    with pytest.raises(CdrError, match="encapsulation"):
        decode_detected_objects(b"\x00\x00\x00\x00" + raw[4:])
    big = bytearray(raw)
    at = 4 + 8 + 4 + len("base_link_with_a_longer_name") + 1
    at += -at % 4
    big[at:at + 4] = (10**6).to_bytes(4, "little")
    with pytest.raises(CdrError, match="cannot fit"):
        decode_detected_objects(bytes(big))


def test_input_not_modified():
    msg = _scene_with_extremes()
    raw = serialize_message(msg)
    before = copy.deepcopy(raw)
    dec = decode_detected_objects(raw)
    encode_detected_objects(dec, [0, 1], np.full(5, 0.5))
    assert raw == before and dec.data == raw


def test_mutated_bytes_decode_or_raise_cdr_error():
    raw = serialize_message(_scene_with_extremes())
    rng = np.random.default_rng(5)
    outcomes = {"decoded": 0, "refused": 0}
    for _ in range(400):
        b = bytearray(raw)
        for at in rng.integers(4, len(b), rng.integers(1, 4)):
            b[at] = int(rng.integers(0, 256))
        if rng.random() < 0.3:
            b = b[:int(rng.integers(4, len(b)))]
        try:
            dec = decode_detected_objects(bytes(b))
        except CdrError:
            outcomes["refused"] += 1
            continue
        outcomes["decoded"] += 1
        encode_detected_objects(dec, np.arange(len(dec)), np.full(len(dec), 0.5))
    assert outcomes["decoded"] > 50 and outcomes["refused"] > 50, outcomes
