"""segment_quality_cdr: the bytes are the message rclpy builds from the same values."""
import numpy as np
import pytest
from lidar_quality_core.segment_quality_cdr import encode_segment_quality_array
from lidar_quality_msgs.msg import SegmentQuality, SegmentQualityArray
from quality_arrays import (decoded_like, random_header, random_model_ids,
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
    for a, b in zip(got.segments, want.segments):   # NaN != NaN: field by field
        assert (a.segment_id, a.class_index, a.class_name, a.point_count,
                a.projected_point_count) == (b.segment_id, b.class_index, b.class_name,
                                             b.point_count, b.projected_point_count)
        np.testing.assert_array_equal([a.confidence, a.predicted_iou],
                                      [b.confidence, b.predicted_iou])
