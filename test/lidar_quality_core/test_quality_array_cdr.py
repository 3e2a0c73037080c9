"""quality_array_cdr: the head and tail it writes frame an empty quality array of either
type, as rclpy reads it; strings and padding as CDR has them."""
import numpy as np
import pytest
from lidar_quality_core.quality_array_cdr import (append_version_fields, array_head,
                                                  cdr_string, cdr_strings, pad)
from lidar_quality_msgs.msg import ClusterUncertaintyArray, SegmentQualityArray
from quality_arrays import decoded_like
from std_msgs.msg import Header


def test_string_and_pad():
    assert cdr_string("é") == b"\x03\x00\x00\x00\xc3\xa9\x00"
    buf = bytearray(b"\x00\x01\x00\x00" + b"x" * 5)
    pad(buf, 4)
    assert len(buf) == 12 and buf[9:] == b"\0\0\0"
    pad(buf, 8)
    assert len(buf) == 12    # 8 bytes after the encapsulation: aligned already


@pytest.mark.parametrize("texts", [
    [], [""], ["", ""], list(range(120)), ["car", "", "pedestrian"],
    [np.int64(7), 2.5, "q"],                   # any objects, as str
    ["x\0y", "z"], ["\0"], ["a", "\0"],        # embedded NUL: string by string
    ["é", "b"], ["ä" * 3, ""],                  # not ASCII: string by string
])
def test_string_runs_are_the_strings_one_after_the_other(texts):
    data, at = cdr_strings(texts)
    one = [cdr_string(str(t)) for t in texts]
    assert data.dtype == np.uint8 and at.dtype == np.int64 and len(at) == len(texts) + 1
    assert data.tobytes() == b"".join(one)
    assert at.tolist() == np.concatenate([[0], np.cumsum([len(e) for e in one])]).tolist()


def test_string_runs_random_texts():
    rng = np.random.default_rng(3)
    for _ in range(300):
        texts = ["".join(chr(int(c)) for c in rng.integers(0, 300, rng.integers(0, 6)))
                 for _ in range(rng.integers(0, 10))]
        data, at = cdr_strings(texts)
        one = [cdr_string(t) for t in texts]
        assert data.tobytes() == b"".join(one)
        assert np.diff(at).tolist() == [len(e) for e in one]


@pytest.mark.parametrize("cls", [SegmentQualityArray, ClusterUncertaintyArray])
def test_empty_array_of_either_type(cls):
    h = Header(frame_id="lidar")
    h.stamp.sec, h.stamp.nanosec = 12, 345
    fields = dict(version=1, drift_level=4, drift_score=0.5, drift_window_frames=50,
                  drift_quantities="a, b", passthrough=True)
    data = append_version_fields(array_head(h, "conf-1", "iou", 0), **fields)
    want = cls(header=h, confidence_model_id="conf-1", iou_model_id="iou", **fields)
    decoded_like(data, want, cls)
