"""detection_quality_cdr: the bytes are the message rclpy builds from the same values."""
import numpy as np
import pytest
from lidar_quality_core.detection_quality_cdr import encode_detection_quality_array
from lidar_quality_msgs.msg import DetectionQuality, DetectionQualityArray
from quality_arrays import (assert_entries_equal, decoded_like, random_header, random_model_ids,
                            random_version_fields)

FIGURES = ("original_score", "confidence", "predicted_iou")


def _case(seed, n):
    rng = np.random.default_rng(seed)
    h = random_header(rng)
    ids = ["d" * int(rng.integers(0, 7)) + str(i) * int(rng.integers(0, 2)) for i in range(n)]
    classes = [["car", "pedestrian", "é-bike", ""][int(k)] for k in rng.integers(0, 4, n)]
    figures = rng.uniform(size=(n, 3))
    figures[rng.uniform(size=figures.shape) < 0.2] = np.nan
    fields = random_version_fields(rng, seed)
    args = (h, *random_model_ids(rng), ids, classes,
            figures)
    return args, fields


def _message(h, cid, iid, ids, classes, figures, **fields):
    entries = [DetectionQuality(detection_index=i, detection_id=d, class_id=c,
                                **{k: float(v) for k, v in zip(FIGURES, row)})
               for i, (d, c, row) in enumerate(zip(ids, classes, figures))]
    return DetectionQualityArray(header=h, confidence_model_id=cid, iou_model_id=iid,
                                 detections=entries, **fields)


@pytest.mark.parametrize("seed,n", [(s, n) for s in range(6) for n in (0, 1, 2, 53)])
def test_bytes_are_the_message(seed, n):
    args, fields = _case(seed, n)
    data = encode_detection_quality_array(*args, **fields)
    want = _message(*args, **fields)
    got = decoded_like(data, want, DetectionQualityArray)
    assert len(got.detections) == n
    assert_entries_equal(got.detections, want.detections,
                         ("detection_index", "detection_id", "class_id"), FIGURES)
