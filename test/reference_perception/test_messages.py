import numpy as np
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.pointcloud import read_fields, xyz_intensity
from std_msgs.msg import Header

from reference_perception.messages import (box_variance_array, detection_array,
                                           probability_cloud, probability_field)

NAMES = ["car", "truck", "pedestrian", "cyclist"]


def _header():
    h = Header(frame_id="lidar")
    h.stamp.sec, h.stamp.nanosec = 5, 100
    return h


def test_detection_array_round_trips_boxes_and_class_distribution():
    boxes = np.array([[10, 1, -0.9, 4.2, 1.8, 1.5, 0.3], [20, -3, -0.8, 0.6, 0.6, 1.7, -2.0]])
    probs = np.array([[0.7, 0.2, 0.0, 0.0], [0.05, 0.0, 0.5, 0.3]])
    var = np.array([[0.1, 0.2, 0.01, 0.3, 0.04, 0.02, 0.05], [1, 2, 3, 4, 5, 6, 7.0]])
    msg = detection_array(_header(), boxes, probs, NAMES, ids=[17, 3], variances=var)
    arr = detections_to_arrays(msg)
    np.testing.assert_allclose(arr.boxes, boxes, atol=1e-9)
    assert arr.ids == ["17", "3"] and arr.labels == ["car", "pedestrian"]
    np.testing.assert_allclose(arr.scores, [0.7, 0.5])
    for k, n in enumerate(NAMES):
        np.testing.assert_allclose(arr.class_scores[n], probs[:, k])
    d = msg.detections[1]
    assert [r.hypothesis.class_id for r in d.results] == ["pedestrian", "cyclist", "car", "truck"]
    cov = np.asarray(d.results[0].pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(np.diag(cov), [1, 2, 3, 0, 0, 7])
    assert msg.header.frame_id == "lidar" and msg.detections[0].header.stamp.sec == 5


def test_box_variances():
    var = np.arange(14, dtype=float).reshape(2, 7)
    msg = box_variance_array(_header(), var, ids=["a", "b"])
    assert [v.detection_id for v in msg.variances] == ["a", "b"]
    v = msg.variances[1]
    assert (v.x, v.y, v.z, v.length, v.width, v.height, v.yaw) == tuple(var[1])
    assert msg.header.stamp.nanosec == 100


def test_probability_cloud_float_and_quantized():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    p = rng.dirichlet(np.ones(3), size=50)
    names = ["road", "traffic-sign", "car"]
    for quantize, tol in ((False, 1e-6), (True, 0.5 / 255 + 1e-9)):
        msg = probability_cloud(_header(), xyz, np.full(50, 0.5), p, names, quantize=quantize)
        x, i = xyz_intensity(msg)
        np.testing.assert_array_equal(x, xyz)
        fields = [probability_field(n) for n in names]
        assert fields == ["road", "traffic_sign", "car"]
        got = read_fields(msg, fields, dtype=np.float64)
        if quantize:
            got = got / 255.0
            assert {f.datatype for f in msg.fields[4:]} == {2}  # UINT8
        np.testing.assert_allclose(got, p, atol=tol)
