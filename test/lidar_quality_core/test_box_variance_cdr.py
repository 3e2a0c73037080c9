"""box_variance_cdr: BoxVarianceArray decoded from its bytes as rclpy reads it; truncated or
mutated bytes decode or raise CdrError."""
import numpy as np
import pytest
from lidar_quality_core.box_variance_cdr import decode_box_variance_array
from lidar_quality_core.detection_cdr import CdrError
from lidar_quality_msgs.msg import BoxVariance, BoxVarianceArray
from rclpy.serialization import serialize_message
from std_msgs.msg import Header


def _msg(ids=("a", "", "größe", "d-17-3")):
    h = Header(frame_id="lidar_top")
    h.stamp.sec, h.stamp.nanosec = 7, 123
    rng = np.random.default_rng(1)
    return BoxVarianceArray(header=h, variances=[
        BoxVariance(detection_index=3 * i, detection_id=d,
                    **dict(zip(("x", "y", "z", "length", "width", "height", "yaw"),
                               rng.uniform(0, 1, 7).tolist())))
        for i, d in enumerate(ids)])


@pytest.mark.parametrize("ids", [(), ("a",), ("a", "", "größe", "d-17-3"), ("x" * 13,) * 5])
def test_decode_equals_the_message(ids):
    msg = _msg(ids)
    dec = decode_box_variance_array(serialize_message(msg))
    assert dec.header == msg.header and dec.ids == [v.detection_id for v in msg.variances]
    assert dec.index.tolist() == [v.detection_index for v in msg.variances]
    np.testing.assert_array_equal(dec.values, np.array(
        [(v.x, v.y, v.z, v.length, v.width, v.height, v.yaw) for v in msg.variances]
    ).reshape(len(ids), 7))


def test_truncated_and_mutated_bytes():
    raw = serialize_message(_msg())
    for cut in (2, 11, 30, len(raw) - 1):
        with pytest.raises(CdrError):
            decode_box_variance_array(raw[:cut])
    rng = np.random.default_rng(2)
    refused = 0
    for _ in range(300):
        b = bytearray(raw)
        for at in rng.integers(4, len(b), 2):
            b[at] = int(rng.integers(0, 256))
        try:
            decode_box_variance_array(bytes(b))
        except CdrError:
            refused += 1
    assert 0 < refused < 300


def test_an_id_with_a_nul_is_read_whole_and_one_not_utf8_refused():
    """The ids are read at once, split at NULs: an id holding a NUL goes one by one,
    whole; bytes that are not UTF-8 are refused, naming the field."""
    data = bytearray(serialize_message(_msg(("aXb", "", "c"))))
    data[data.index(b"aXb") + 1] = 0
    assert decode_box_variance_array(bytes(data)).ids == ["a\0b", "", "c"]
    data[data.index(b"a\0b") + 1] = 0xFF
    with pytest.raises(CdrError, match="a detection_id is not UTF-8"):
        decode_box_variance_array(bytes(data))
