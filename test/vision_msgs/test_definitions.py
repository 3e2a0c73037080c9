"""The vision_msgs in use carry the exact Jazzy (4.1.1) field definitions."""
import importlib

import pytest

JAZZY = {
    "BoundingBox2D": {"center": "vision_msgs/Pose2D", "size_x": "double", "size_y": "double"},
    "BoundingBox2DArray": {"header": "std_msgs/Header",
                           "boxes": "sequence<vision_msgs/BoundingBox2D>"},
    "BoundingBox3D": {"center": "geometry_msgs/Pose", "size": "geometry_msgs/Vector3"},
    "BoundingBox3DArray": {"header": "std_msgs/Header",
                           "boxes": "sequence<vision_msgs/BoundingBox3D>"},
    "Classification": {"header": "std_msgs/Header",
                       "results": "sequence<vision_msgs/ObjectHypothesis>"},
    "Detection2D": {"header": "std_msgs/Header",
                    "results": "sequence<vision_msgs/ObjectHypothesisWithPose>",
                    "bbox": "vision_msgs/BoundingBox2D", "id": "string"},
    "Detection2DArray": {"header": "std_msgs/Header",
                         "detections": "sequence<vision_msgs/Detection2D>"},
    "Detection3D": {"header": "std_msgs/Header",
                    "results": "sequence<vision_msgs/ObjectHypothesisWithPose>",
                    "bbox": "vision_msgs/BoundingBox3D", "id": "string"},
    "Detection3DArray": {"header": "std_msgs/Header",
                         "detections": "sequence<vision_msgs/Detection3D>"},
    "LabelInfo": {"header": "std_msgs/Header",
                  "class_map": "sequence<vision_msgs/VisionClass>", "threshold": "float"},
    "ObjectHypothesis": {"class_id": "string", "score": "double"},
    "ObjectHypothesisWithPose": {"hypothesis": "vision_msgs/ObjectHypothesis",
                                 "pose": "geometry_msgs/PoseWithCovariance"},
    "Point2D": {"x": "double", "y": "double"},
    "Pose2D": {"position": "vision_msgs/Point2D", "theta": "double"},
    "VisionClass": {"class_id": "uint16", "class_name": "string"},
    "VisionInfo": {"header": "std_msgs/Header", "method": "string",
                   "database_location": "string", "database_version": "int32"},
}


@pytest.mark.parametrize("name", sorted(JAZZY))
def test_fields_in_order(name):
    cls = getattr(importlib.import_module("vision_msgs.msg"), name)
    fields = cls.get_fields_and_field_types()
    assert list(fields.items()) == list(JAZZY[name].items())


@pytest.mark.parametrize("name", sorted(JAZZY))
def test_no_constants_no_defaults(name):
    cls = getattr(importlib.import_module("vision_msgs.msg"), name)
    meta = type(cls)
    constants = [k for k in vars(meta) if k.isupper() and not k.startswith("_")]
    assert constants == [] and getattr(meta, f"_{meta.__name__}__constants") == {}
    assert meta.__prepare__(name, ()) == {}  # rosidl lists field defaults here
    fresh = cls()
    for field, typ in JAZZY[name].items():
        value = getattr(fresh, field)
        if typ in ("double", "float"):
            assert value == 0.0
        elif typ in ("uint16", "int32"):
            assert value == 0
        elif typ == "string":
            assert value == ""
        elif typ.startswith("sequence<"):
            assert len(value) == 0


def test_all_sixteen_messages():
    mod = importlib.import_module("vision_msgs.msg")
    exported = {n for n in dir(mod) if not n.startswith("_") and isinstance(getattr(mod, n), type)}
    assert exported == set(JAZZY)
