"""Our messages in the rosbags typestore: registered from the .msg files, CDR round trip,
and the same wire format and type hash as the rclpy message classes."""
import numpy as np
from lidar_quality_core.rosbag_types import PACKAGES, msg_dir, typestore
from rclpy.serialization import deserialize_message, serialize_message


def test_every_message_registered_from_its_file():
    ts = typestore()
    for package in PACKAGES:
        names = sorted(p.stem for p in msg_dir(package).glob("*.msg"))
        assert names, package
        for name in names:
            assert f"{package}/msg/{name}" in ts.types
    assert len([t for t in ts.types if t.startswith("vision_msgs/msg/")]) == 16


def test_cdr_matches_rclpy_wire_format():
    from vision_msgs.msg import Detection3DArray as RclpyArray
    from lidar_quality_core.boxes import arrays_to_detections
    from std_msgs.msg import Header
    h = Header(frame_id="lidar")
    h.stamp.sec, h.stamp.nanosec = 3, 500
    sent = arrays_to_detections(h, np.array([[1, 2, 0, 4, 2, 1.5, 0.2]]), ["car"], [0.75], ids=["a"])
    raw = serialize_message(sent)
    ts = typestore()
    msg = ts.deserialize_cdr(raw, "vision_msgs/msg/Detection3DArray")
    assert msg.detections[0].id == "a" and msg.detections[0].results[0].hypothesis.score == 0.75
    back = bytes(ts.serialize_cdr(msg, "vision_msgs/msg/Detection3DArray"))
    # Same length and content both ways; raw bytes may differ only in CDR alignment
    # padding, which Fast CDR leaves uninitialised.
    assert len(back) == len(raw)
    assert deserialize_message(back, RclpyArray) == sent


def test_quality_message_type_hash_matches_rosidl():
    # rosidl writes the RIHS01 hash of each interface beside it (.json); rosbags must agree.
    import json
    ts = typestore()
    for package, name in (("lidar_quality_msgs", "DetectionQualityArray"),
                          ("lidar_quality_msgs", "SegmentQualityArray"),
                          ("lidar_quality_msgs", "ClusterUncertaintyArray"),
                          ("vision_msgs", "Detection3DArray")):
        info = json.loads((msg_dir(package) / f"{name}.json").read_text())
        want = info["type_hashes"][0]["hash_string"]
        assert ts.hash_rihs01(f"{package}/msg/{name}") == want


def test_quality_array_with_drift_fields_through_rosbags():
    """The bytes process_bag writes (rclpy's, re-serialized by rosbags for zero padding)
    hold the version and drift fields: rosbags reads rclpy's bytes field for field, and
    rclpy reads rosbags' back to the same message, NaN score included."""
    import math

    from lidar_quality_msgs.msg import DetectionQuality, DetectionQualityArray
    from std_msgs.msg import Header

    ts = typestore()
    name = "lidar_quality_msgs/msg/DetectionQualityArray"
    for score in (0.75, math.nan):
        sent = DetectionQualityArray(
            header=Header(frame_id="lidar"), confidence_model_id="c", iou_model_id="i",
            detections=[DetectionQuality(detection_id="a", class_id="car", confidence=0.5)],
            version=DetectionQualityArray.MESSAGE_VERSION,
            drift_level=DetectionQualityArray.DRIFT_WARN, drift_score=score,
            drift_window_frames=50, drift_quantities="detector score", passthrough=True)
        raw = serialize_message(sent)
        msg = ts.deserialize_cdr(raw, name)
        assert (msg.version, msg.drift_level, msg.drift_window_frames, msg.drift_quantities,
                msg.passthrough) == (1, 4, 50, "detector score", True)
        assert msg.drift_score == score or math.isnan(msg.drift_score) == math.isnan(score)
        back = bytes(ts.serialize_cdr(msg, name))
        assert len(back) == len(raw)
        got = deserialize_message(back, DetectionQualityArray)
        assert got.detections == sent.detections and got.passthrough
        assert (got.drift_score == score) or (math.isnan(got.drift_score) and math.isnan(score))
