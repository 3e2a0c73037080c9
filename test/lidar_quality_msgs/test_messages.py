"""Every message of lidar_quality_msgs, and Detection3DArray, through real rclpy pub/sub;
the quality arrays' version and drift fields."""
import math

import pytest
from lidar_quality_msgs.msg import (BoxVariance, BoxVarianceArray, ClusterUncertainty,
                                    ClusterUncertaintyArray, DetectionQuality,
                                    DetectionQualityArray, SegmentQuality, SegmentQualityArray)
from std_msgs.msg import Header
from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose


def _header(sec=12, frame="lidar_top"):
    h = Header(frame_id=frame)
    h.stamp.sec, h.stamp.nanosec = sec, 345
    return h


def _drift(cls, level="DRIFT_ERROR"):
    """The version and drift fields as a node sets them (score exact in float32)."""
    return dict(version=cls.MESSAGE_VERSION, drift_level=getattr(cls, level),
                drift_score=1.625, drift_window_frames=50,
                drift_quantities="detector score, points per frame", passthrough=True)


def _detection_quality_array():
    return DetectionQualityArray(
        header=_header(), confidence_model_id="lmd_clf@abc123", iou_model_id="lmd_reg@def456",
        detections=[DetectionQuality(detection_index=i, detection_id=f"d{i}", class_id="car",
                                     original_score=0.9 - 0.1 * i, confidence=0.5 + 0.01 * i,
                                     predicted_iou=0.7) for i in range(3)],
        **_drift(DetectionQualityArray))


def _segment_quality_array():
    return SegmentQualityArray(
        header=_header(), confidence_model_id="lms_clf", iou_model_id="lms_reg",
        segments=[SegmentQuality(segment_id=7, class_index=3, class_name="building",
                                 point_count=1234, projected_point_count=999,
                                 confidence=0.25, predicted_iou=0.125)],
        **_drift(SegmentQualityArray, "DRIFT_WARN"))


def _cluster_uncertainty_array():
    return ClusterUncertaintyArray(
        header=_header(), confidence_model_id="mimo_clf", iou_model_id="mimo_reg",
        clusters=[ClusterUncertainty(detection_index=0, detection_id="m0", class_id="pedestrian",
                                     cluster_size=2, shannon_entropy=0.9, aleatoric_entropy=0.6,
                                     mutual_information=0.3, epistemic_total_variance=0.04,
                                     aleatoric_total_variance=0.2, confidence=0.8,
                                     predicted_iou=0.55)],
        **_drift(ClusterUncertaintyArray, "DRIFT_OK"))


def _box_variance_array():
    return BoxVarianceArray(
        header=_header(), variances=[BoxVariance(detection_index=i, detection_id=f"h{i}",
                                                 x=0.1 * i, y=0.2, z=0.05, length=0.3, width=0.04,
                                                 height=0.02, yaw=0.01) for i in range(2)])


def _detection3d_array():
    det = Detection3D(header=_header(), id="track-42")
    det.bbox.center.position.x, det.bbox.center.orientation.w = 10.5, 1.0
    det.bbox.size.x, det.bbox.size.y, det.bbox.size.z = 4.2, 1.8, 1.5
    hyp = ObjectHypothesisWithPose()
    hyp.hypothesis.class_id, hyp.hypothesis.score = "car", 0.875
    hyp.pose.covariance[0] = 0.25
    det.results.append(hyp)
    return Detection3DArray(header=_header(), detections=[det, Detection3D(id="empty")])


@pytest.mark.parametrize("factory", [_detection_quality_array, _segment_quality_array,
                                     _cluster_uncertainty_array, _detection3d_array,
                                     _box_variance_array,
                                     lambda: _detection_quality_array().detections[0],
                                     lambda: _segment_quality_array().segments[0],
                                     lambda: _cluster_uncertainty_array().clusters[0]])
def test_roundtrip_over_dds(ros, factory):
    sent = factory()
    topic = f"roundtrip_{type(sent).__name__.lower()}"
    pub = ros.publisher(type(sent), topic)
    col = ros.collector(type(sent), topic)
    assert ros.wait_for_match(pub)
    pub.publish(sent)
    assert col.wait_for(1, timeout=10.0), f"no {type(sent).__name__} received"
    assert col.messages[0] == sent


def test_field_names_self_explaining():
    fields = ClusterUncertainty.get_fields_and_field_types()
    for name in ("cluster_size", "shannon_entropy", "aleatoric_entropy", "mutual_information",
                 "epistemic_total_variance", "aleatoric_total_variance", "confidence",
                 "predicted_iou"):
        assert fields[name] in ("uint32", "double")
    assert set(DetectionQuality.get_fields_and_field_types()) >= {
        "detection_index", "detection_id", "class_id", "original_score", "confidence",
        "predicted_iou"}
    assert set(SegmentQuality.get_fields_and_field_types()) >= {
        "segment_id", "class_index", "class_name", "point_count", "confidence", "predicted_iou"}
    assert [k for k, t in BoxVariance.get_fields_and_field_types().items() if t == "double"] == [
        "x", "y", "z", "length", "width", "height", "yaw"]
    assert BoxVarianceArray.get_fields_and_field_types()["header"] == "std_msgs/Header"
    for arr in (DetectionQualityArray, SegmentQualityArray, ClusterUncertaintyArray):
        f = arr.get_fields_and_field_types()
        assert f["header"] == "std_msgs/Header"
        assert f["confidence_model_id"] == f["iou_model_id"] == "string"


def test_nan_survives_transport(ros):
    sent = _detection_quality_array()
    sent.detections[1].confidence = math.nan
    pub = ros.publisher(DetectionQualityArray, "nan_quality")
    col = ros.collector(DetectionQualityArray, "nan_quality")
    assert ros.wait_for_match(pub)
    pub.publish(sent)
    assert col.wait_for(1, timeout=10.0)
    assert math.isnan(col.messages[0].detections[1].confidence)
    assert col.messages[0].detections[0].confidence == sent.detections[0].confidence


QUALITY_ARRAYS = (DetectionQualityArray, SegmentQualityArray, ClusterUncertaintyArray)


def test_quality_arrays_are_versioned_with_the_drift_fields():
    """Version 1 appends the same fields and constants to the three arrays, after the
    fields of version 0 (which old readers stop at)."""
    fields = {"version": "uint8", "drift_level": "uint8", "drift_score": "float",
              "drift_window_frames": "uint32", "drift_quantities": "string",
              "passthrough": "boolean"}
    levels = ("DRIFT_UNKNOWN", "DRIFT_OFF", "DRIFT_WARMING_UP", "DRIFT_OK", "DRIFT_WARN",
              "DRIFT_ERROR")
    for cls, items in zip(QUALITY_ARRAYS, ("detections", "segments", "clusters")):
        f = cls.get_fields_and_field_types()
        # version 0's fields first, in their order
        assert list(f)[:4] == ["header", "confidence_model_id", "iou_model_id", items]
        assert dict(list(f.items())[4:]) == fields, cls.__name__
        assert cls.MESSAGE_VERSION == 1
        assert [getattr(cls, c) for c in levels] == list(range(6))  # ordered by severity
        empty = cls()        # a publisher that sets nothing says nothing
        assert (empty.version, empty.drift_level, empty.passthrough) == (0, 0, False)


def test_nan_drift_score_survives_transport(ros):
    """A frame before the first score: NaN score, warming up."""
    sent = _cluster_uncertainty_array()
    sent.drift_level, sent.drift_score = sent.DRIFT_WARMING_UP, math.nan
    sent.drift_quantities, sent.passthrough = "", False
    pub = ros.publisher(ClusterUncertaintyArray, "nan_drift")
    col = ros.collector(ClusterUncertaintyArray, "nan_drift")
    assert ros.wait_for_match(pub)
    pub.publish(sent)
    assert col.wait_for(1, timeout=10.0)
    got = col.messages[0]
    assert math.isnan(got.drift_score) and got.drift_level == got.DRIFT_WARMING_UP
    assert got.version == 1 and got.clusters == sent.clusters
