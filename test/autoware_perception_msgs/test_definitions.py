"""The autoware_perception_msgs in use carry Autoware's detected-object definitions: fields
in order, constants, and RIHS01 type hashes equal between rosidl and rosbags."""
import importlib
import json

import pytest
from lidar_quality_core.autoware_objects import LABELS
from lidar_quality_core.rosbag_types import msg_dir, typestore

AUTOWARE = {
    "DetectedObjects": {"header": "std_msgs/Header",
                        "objects": "sequence<autoware_perception_msgs/DetectedObject>"},
    "DetectedObject": {
        "existence_probability": "float",
        "classification": "sequence<autoware_perception_msgs/ObjectClassification>",
        "kinematics": "autoware_perception_msgs/DetectedObjectKinematics",
        "shape": "autoware_perception_msgs/Shape"},
    "ObjectClassification": {"label": "uint8", "probability": "float"},
    "DetectedObjectKinematics": {
        "pose_with_covariance": "geometry_msgs/PoseWithCovariance",
        "has_position_covariance": "boolean", "orientation_availability": "uint8",
        "twist_with_covariance": "geometry_msgs/TwistWithCovariance",
        "has_twist": "boolean", "has_twist_covariance": "boolean"},
    "Shape": {"type": "uint8", "footprint": "geometry_msgs/Polygon",
              "dimensions": "geometry_msgs/Vector3"},
}
CONSTANTS = {
    "ObjectClassification": dict(UNKNOWN=0, CAR=1, TRUCK=2, BUS=3, TRAILER=4, MOTORCYCLE=5,
                                 BICYCLE=6, PEDESTRIAN=7, ANIMAL=8, HAZARD=9,
                                 OVER_DRIVABLE=10, UNDER_DRIVABLE=11),
    "DetectedObjectKinematics": dict(UNAVAILABLE=0, SIGN_UNKNOWN=1, AVAILABLE=2),
    "Shape": dict(BOUNDING_BOX=0, CYLINDER=1, POLYGON=2),
    "DetectedObjects": {}, "DetectedObject": {},
}


def _cls(name):
    return getattr(importlib.import_module("autoware_perception_msgs.msg"), name)


@pytest.mark.parametrize("name", sorted(AUTOWARE))
def test_fields_in_order(name):
    assert list(_cls(name).get_fields_and_field_types().items()) == list(AUTOWARE[name].items())


@pytest.mark.parametrize("name", sorted(CONSTANTS))
def test_constants(name):
    meta = type(_cls(name))
    assert getattr(meta, f"_{meta.__name__}__constants") == CONSTANTS[name]


def test_label_table_matches_the_message_constants():
    assert {k: i for i, k in enumerate(LABELS)} == CONSTANTS["ObjectClassification"]


@pytest.mark.parametrize("name", sorted(AUTOWARE))
def test_type_hash_rosidl_equals_rosbags(name):
    # rosidl writes the RIHS01 hash it computed beside each interface (.json)
    info = json.loads((msg_dir("autoware_perception_msgs") / f"{name}.json").read_text())
    want = info["type_hashes"][0]["hash_string"]
    assert want.startswith("RIHS01_")
    assert typestore().hash_rihs01(f"autoware_perception_msgs/msg/{name}") == want
