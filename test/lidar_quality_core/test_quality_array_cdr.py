"""quality_array_cdr: the head and tail it writes frame an empty quality array of either
type, as rclpy reads it; strings and padding as CDR has them."""
import pytest
from lidar_quality_core.quality_array_cdr import (append_version_fields, array_head,
                                                  cdr_string, pad)
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


@pytest.mark.parametrize("cls", [SegmentQualityArray, ClusterUncertaintyArray])
def test_empty_array_of_either_type(cls):
    h = Header(frame_id="lidar")
    h.stamp.sec, h.stamp.nanosec = 12, 345
    fields = dict(version=1, drift_level=4, drift_score=0.5, drift_window_frames=50,
                  drift_quantities="a, b", passthrough=True)
    data = append_version_fields(array_head(h, "conf-1", "iou", 0), **fields)
    want = cls(header=h, confidence_model_id="conf-1", iou_model_id="iou", **fields)
    decoded_like(data, want, cls)
