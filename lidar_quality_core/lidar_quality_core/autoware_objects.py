"""Autoware's ``autoware_perception_msgs/DetectedObjects`` to and from our detection arrays.

In: each ``DetectedObject`` becomes one row of :class:`~lidar_quality_core.boxes.
DetectionArrays` (same order; id = its index, as the message has none): the box from
``kinematics.pose_with_covariance.pose`` and ``shape``, one hypothesis per
``classification`` entry, its class the model's name for the Autoware label
(:data:`DEFAULT_CLASS_MAP`, a parameter in the nodes). A label without a model class keeps
the lower-case Autoware name (``"bus"``), which is not among the model's classes: the
object is then invalid for the meta model and passes through unscored (counted by the
caller).

Shapes: ``BOUNDING_BOX`` dimensions are length, width, height; ``CYLINDER`` has the
diameter in ``dimensions.x`` (a square footprint of that side); ``POLYGON`` takes the
extents of its footprint (object frame) and ``dimensions.z`` as height. Any other type is
an invalid box.

Out: :func:`score_objects` writes the meta confidence into ``existence_probability`` and
re-scales the classification probabilities as the vision_msgs output does
(``detection_cdr.rescaled_scores``: the top class gets the confidence, the others keep
their ratio to it). A NaN confidence never reaches Autoware: the object keeps its own
existence probability (0 if that is not finite either; or a fixed ``fallback``) and its
classification, and is counted.
No rclpy: messages are read and written through their attributes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .boxes import DetectionArrays, arrays_from_fields
from .detection_cdr import rescaled_scores

__all__ = ["LABELS", "DEFAULT_CLASS_MAP", "AutowareDetections", "parse_class_map",
           "label_names", "objects_to_arrays", "score_objects", "kept_objects"]

#: ObjectClassification labels by value (autoware_perception_msgs constants).
LABELS = ("UNKNOWN", "CAR", "TRUCK", "BUS", "TRAILER", "MOTORCYCLE", "BICYCLE", "PEDESTRIAN",
          "ANIMAL", "HAZARD", "OVER_DRIVABLE", "UNDER_DRIVABLE")
#: Autoware label -> our models' class name; the labels not listed have no model class.
DEFAULT_CLASS_MAP = {"CAR": "car", "TRUCK": "truck", "PEDESTRIAN": "pedestrian",
                     "BICYCLE": "cyclist"}
BOUNDING_BOX, CYLINDER, POLYGON = 0, 1, 2


@dataclass
class AutowareDetections:
    """A DetectedObjects message with its arrays read (the methods' input, like
    ``detection_cdr.DecodedDetections`` for vision_msgs): ``header``, ``arrays``, ``msg``."""

    header: object
    arrays: DetectionArrays
    msg: object

    @classmethod
    def read(cls, msg, class_map: dict[str, str] | None = None) -> "AutowareDetections":
        return cls(msg.header, objects_to_arrays(msg, class_map), msg)

    def __len__(self) -> int:
        return len(self.arrays)


def parse_class_map(text: str) -> dict[str, str]:
    """``"CAR:car BUS:truck"`` (spaces or commas) -> ``{"CAR": "car", "BUS": "truck"}``;
    ``ValueError`` naming an unknown Autoware label or a malformed entry."""
    out = {}
    for item in text.replace(",", " ").split():
        label, sep, name = item.partition(":")
        if not sep or not name:
            raise ValueError(f"class map entry {item!r}: expected AUTOWARE_LABEL:class_name")
        if label.upper() not in LABELS:
            raise ValueError(f"class map entry {item!r}: {label!r} is not an Autoware label "
                             f"({', '.join(LABELS)})")
        out[label.upper()] = name
    return out


def label_names(class_map: dict[str, str] | None = None) -> list[str]:
    """Class name of every label value (index = value): the mapped name, else the
    lower-case Autoware name."""
    m = DEFAULT_CLASS_MAP if class_map is None else class_map
    return [m.get(label, label.lower()) for label in LABELS]


def _size(shape) -> tuple[float, float, float]:
    d = shape.dimensions
    if shape.type == BOUNDING_BOX:
        return d.x, d.y, d.z
    if shape.type == CYLINDER:
        return d.x, d.x, d.z
    if shape.type == POLYGON:
        pts = shape.footprint.points
        if not pts:
            return np.nan, np.nan, d.z
        xs, ys = [p.x for p in pts], [p.y for p in pts]
        return max(xs) - min(xs), max(ys) - min(ys), d.z
    return np.nan, np.nan, np.nan


def objects_to_arrays(msg, class_map: dict[str, str] | None = None) -> DetectionArrays:
    """``DetectionArrays`` of a DetectedObjects message (module docstring)."""
    names = label_names(class_map)
    rows, hyp_det, hyp_cls, hyp_sc, bad_shape = [], [], [], [], {}
    for i, obj in enumerate(msg.objects):
        pose = obj.kinematics.pose_with_covariance.pose
        p, q = pose.position, pose.orientation
        if obj.shape.type not in (BOUNDING_BOX, CYLINDER, POLYGON):
            bad_shape[i] = f"unknown shape type {obj.shape.type}"
        elif obj.shape.type == POLYGON and not obj.shape.footprint.points:
            bad_shape[i] = "polygon shape without footprint points"
        rows.append((p.x, p.y, p.z, *_size(obj.shape), q.x, q.y, q.z, q.w))
        for c in obj.classification:
            hyp_det.append(i)
            hyp_cls.append(names[c.label] if c.label < len(names) else f"label_{c.label}")
            hyp_sc.append(c.probability)
    raw = np.array(rows, dtype=np.float64).reshape(len(rows), 10)
    arrays = arrays_from_fields(raw, [str(i) for i in range(len(rows))], hyp_det, hyp_cls,
                                hyp_sc)
    for i, why in bad_shape.items():  # said in words, not as the NaN size it causes
        arrays.reasons[i] = why
        arrays.valid[i] = False
    return arrays


def score_objects(msg, confidence, *, fallback: float | None = None) -> int:
    """Write ``confidence`` (one per object, NaN allowed) into ``msg`` in place (module
    docstring); returns how many objects got the fallback instead (NaN confidence)."""
    conf = np.asarray(confidence, dtype=np.float64).reshape(-1)
    objects = msg.objects
    if len(conf) != len(objects):
        raise ValueError(f"{len(conf)} confidences for {len(objects)} objects")
    det = [i for i, o in enumerate(objects) for _ in o.classification]
    probs = [c.probability for o in objects for c in o.classification]
    scaled = rescaled_scores(probs, det, conf).tolist() if det else []
    j = 0
    n_fallback = 0
    for obj, c in zip(objects, conf.tolist()):
        k = len(obj.classification)
        if np.isfinite(c):
            obj.existence_probability = c
            for cls, s in zip(obj.classification, scaled[j:j + k]):
                cls.probability = s
        else:
            n_fallback += 1
            if fallback is not None:
                obj.existence_probability = float(fallback)
            elif not np.isfinite(obj.existence_probability):
                obj.existence_probability = 0.0
        j += k
    return n_fallback


def kept_objects(msg, kept):
    """``msg`` with only the objects where ``kept`` is True (same order; in place)."""
    msg.objects = [o for o, k in zip(msg.objects, np.asarray(kept, bool).tolist()) if k]
    return msg
