"""cluster_uncertainty_cdr: the bytes are the message rclpy builds from the same values."""
import numpy as np
import pytest
from lidar_quality_core.cluster_uncertainty_cdr import encode_cluster_uncertainty_array
from lidar_quality_msgs.msg import ClusterUncertainty, ClusterUncertaintyArray
from quality_arrays import (assert_entries_equal, decoded_like, random_header, random_model_ids,
                            random_version_fields)

FIGURES = ("shannon_entropy", "aleatoric_entropy", "mutual_information",
           "epistemic_total_variance", "aleatoric_total_variance", "confidence",
           "predicted_iou")


def _case(seed, n):
    rng = np.random.default_rng(seed)
    h = random_header(rng)
    ids = [f"{int(rng.integers(0, 4))}:" + "x" * int(rng.integers(0, 7)) for _ in range(n)]
    classes = [["car", "pedestrian", "é-bike", ""][int(k)] for k in rng.integers(0, 4, n)]
    figures = rng.uniform(size=(n, 7))
    figures[rng.uniform(size=figures.shape) < 0.2] = np.nan
    fields = random_version_fields(rng, seed)
    args = (h, *random_model_ids(rng), ids, classes,
            rng.integers(1, 5, n), figures)
    return args, fields


def _message(h, cid, iid, ids, classes, sizes, figures, **fields):
    clusters = [ClusterUncertainty(detection_index=i, detection_id=d, class_id=c,
                                   cluster_size=int(s),
                                   **{k: float(v) for k, v in zip(FIGURES, row)})
                for i, (d, c, s, row) in enumerate(zip(ids, classes, sizes, figures))]
    return ClusterUncertaintyArray(header=h, confidence_model_id=cid, iou_model_id=iid,
                                   clusters=clusters, **fields)


@pytest.mark.parametrize("seed,n", [(s, n) for s in range(6) for n in (0, 1, 2, 37)])
def test_bytes_are_the_message(seed, n):
    args, fields = _case(seed, n)
    data = encode_cluster_uncertainty_array(*args, **fields)
    want = _message(*args, **fields)
    got = decoded_like(data, want, ClusterUncertaintyArray)
    assert len(got.clusters) == n
    assert_entries_equal(got.clusters, want.clusters,
                         ("detection_index", "detection_id", "class_id", "cluster_size"),
                         FIGURES)
