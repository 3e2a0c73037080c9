"""A Detection3DArray scene as Autoware's DetectedObjects (the same boxes and classes), and
the scene with its scores rounded to float32, as ObjectClassification carries them."""
from __future__ import annotations

import copy

import numpy as np
from autoware_perception_msgs.msg import (DetectedObject, DetectedObjects, ObjectClassification,
                                          Shape)
from lidar_quality_core.autoware_objects import LABELS

#: our class names -> Autoware label value (inverse of DEFAULT_CLASS_MAP)
LABEL_OF = {"car": LABELS.index("CAR"), "truck": LABELS.index("TRUCK"),
            "pedestrian": LABELS.index("PEDESTRIAN"), "cyclist": LABELS.index("BICYCLE")}


def float32_scores(msg):
    """A copy of Detection3DArray ``msg`` with every hypothesis score rounded to float32."""
    out = copy.deepcopy(msg)
    for d in out.detections:
        for r in d.results:
            r.hypothesis.score = float(np.float32(r.hypothesis.score))
    return out


def detected_objects(msg, existence=0.5) -> DetectedObjects:
    """DetectedObjects of Detection3DArray ``msg``: same header and order, pose = bbox
    centre, BOUNDING_BOX of the bbox size, one classification per hypothesis."""
    out = DetectedObjects(header=copy.deepcopy(msg.header))
    for d in msg.detections:
        o = DetectedObject(existence_probability=existence)
        o.kinematics.pose_with_covariance.pose = copy.deepcopy(d.bbox.center)
        o.kinematics.orientation_availability = o.kinematics.SIGN_UNKNOWN
        o.shape.type = Shape.BOUNDING_BOX
        o.shape.dimensions = copy.deepcopy(d.bbox.size)
        o.classification = [ObjectClassification(label=LABEL_OF[r.hypothesis.class_id],
                                                 probability=r.hypothesis.score)
                            for r in d.results]
        out.objects.append(o)
    return out
