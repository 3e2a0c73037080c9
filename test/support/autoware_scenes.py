"""Scenes for the Autoware tests: a Detection3DArray scene with its scores rounded to
float32 (as ObjectClassification carries them), so that the vision_msgs path and the
DetectedObjects path (``autoware_objects.objects_from_detections``) see equal inputs."""
from __future__ import annotations

import copy
import math

import numpy as np
from autoware_perception_msgs.msg import (DetectedObject, DetectedObjects, ObjectClassification,
                                          Shape)
from geometry_msgs.msg import Point32
from lidar_quality_core.autoware_objects import objects_from_detections
from std_msgs.msg import Header


def float32_scores(msg):
    """A copy of Detection3DArray ``msg`` with every hypothesis score rounded to float32."""
    out = copy.deepcopy(msg)
    for d in out.detections:
        for r in d.results:
            r.hypothesis.score = float(np.float32(r.hypothesis.score))
    return out


def detected_objects(msg):
    """DetectedObjects of Detection3DArray ``msg`` (a deep copy: the message may be reused)."""
    return objects_from_detections(copy.deepcopy(msg))


def _obj(x, y, yaw, size, classes, shape=Shape.BOUNDING_BOX, existence=0.5, footprint=None):
    o = DetectedObject(existence_probability=existence)
    p = o.kinematics.pose_with_covariance.pose
    p.position.x, p.position.y, p.position.z = float(x), float(y), 0.8
    p.orientation.z, p.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    o.shape.type = shape
    o.shape.dimensions.x, o.shape.dimensions.y, o.shape.dimensions.z = map(float, size)
    if footprint is not None:
        o.shape.footprint.points = [Point32(x=a, y=b) for a, b in footprint]
    o.classification = [ObjectClassification(label=lb, probability=pr) for lb, pr in classes]
    return o


def hand_built_scene():
    """Five objects: a box with two classes, a cylinder, a polygon, a BUS (no model class),
    an unknown shape type."""
    C = ObjectClassification
    return DetectedObjects(header=Header(frame_id="base_link"), objects=[
        _obj(10, 2, 0.3, (4.2, 1.8, 1.5), [(C.CAR, 0.75), (C.TRUCK, 0.25)]),
        _obj(-5, 1, -1.0, (0.6, 0.0, 1.7), [(C.PEDESTRIAN, 0.5)], shape=Shape.CYLINDER),
        _obj(3, -4, 0.0, (0, 0, 1.2), [(C.BICYCLE, 0.625)], shape=Shape.POLYGON,
             footprint=[(-0.9, -0.3), (0.9, -0.3), (0.9, 0.3), (-0.9, 0.3)]),
        _obj(20, 0, 0.0, (11.0, 2.5, 3.2), [(C.BUS, 0.875)]),
        _obj(7, 7, 0.0, (1, 1, 1), [(C.CAR, 0.5)], shape=7),
    ])
