"""Scenes for the Autoware tests: a Detection3DArray scene with its scores rounded to
float32 (as ObjectClassification carries them), so that the vision_msgs path and the
DetectedObjects path (``autoware_objects.objects_from_detections``) see equal inputs."""
from __future__ import annotations

import copy

import numpy as np
from lidar_quality_core.autoware_objects import objects_from_detections


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
