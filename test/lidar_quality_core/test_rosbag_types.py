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
                          ("vision_msgs", "Detection3DArray")):
        info = json.loads((msg_dir(package) / f"{name}.json").read_text())
        want = info["type_hashes"][0]["hash_string"]
        assert ts.hash_rihs01(f"{package}/msg/{name}") == want
