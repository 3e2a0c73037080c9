"""segment_quality_cdr: the bytes are the message rclpy builds from the same values."""
import numpy as np
import pytest
from lidar_quality_core.segment_quality_cdr import encode_segment_quality_array
from lidar_quality_msgs.msg import SegmentQuality, SegmentQualityArray
from quality_arrays import (assert_entries_equal, decoded_like, random_header, random_model_ids,
                            random_version_fields)


def _case(seed, n):
    rng = np.random.default_rng(seed)
    names = ["c" * int(k) for k in rng.integers(0, 12, size=int(rng.integers(1, 6)))]
    names[0] = "road-é"  # non-ASCII, and a '-'
    h = random_header(rng)
    cls = rng.integers(0, len(names), n)
    conf, iou = rng.uniform(size=n), rng.uniform(size=n)
    conf[rng.uniform(size=n) < 0.3] = np.nan
    fields = random_version_fields(rng, seed)
    args = (h, *random_model_ids(rng), cls, names,
            rng.integers(0, 5000, n), rng.integers(0, 5000, n), conf, iou)
    return args, fields


def _message(h, cid, iid, cls, names, pc, ppc, conf, iou, **fields):
    segs = [SegmentQuality(segment_id=i, class_index=int(c), class_name=names[c],
                           point_count=int(a), projected_point_count=int(b),
                           confidence=float(x), predicted_iou=float(y))
            for i, (c, a, b, x, y) in enumerate(zip(cls, pc, ppc, conf, iou))]
    return SegmentQualityArray(header=h, confidence_model_id=cid, iou_model_id=iid,
                               segments=segs, **fields)


@pytest.mark.parametrize("seed,n", [(s, n) for s in range(6) for n in (0, 1, 2, 57)])
def test_bytes_are_the_message(seed, n):
    args, fields = _case(seed, n)
    data = encode_segment_quality_array(*args, **fields)
    want = _message(*args, **fields)
    got = decoded_like(data, want, SegmentQualityArray)
    assert len(got.segments) == n
    assert_entries_equal(got.segments, want.segments,
                         ("segment_id", "class_index", "class_name", "point_count",
                          "projected_point_count"), ("confidence", "predicted_iou"))


def test_class_index_outside_the_names_raises():
    args, fields = _case(0, 3)
    args = list(args)
    for bad in ([0, 1, len(args[4])], [0, -1, 0]):
        args[3] = np.array(bad)
        with pytest.raises(ValueError, match="class_index"):
            encode_segment_quality_array(*args, **fields)
