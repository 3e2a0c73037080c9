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
No rclpy: messages are read and written through their attributes. The nodes read and
write the same rules from and to the serialized bytes (``autoware_cdr``), ~70x cheaper
than rclpy's message objects.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .boxes import DetectionArrays, arrays_from_fields, yaw_to_quaternion
from .detection_cdr import rescaled_scores
from .parameters import param

__all__ = ["LABELS", "DEFAULT_CLASS_MAP", "AutowareOutput",
           "parse_class_map",
           "label_names", "objects_to_arrays", "score_objects", "kept_objects",
           "objects_from_boxes", "objects_from_detections", "arrays_of_objects",
           "scored_values", "input_type_param", "class_map_param",
           "existence_fallback_param"]

#: ObjectClassification labels by value (autoware_perception_msgs constants).
LABELS = ("UNKNOWN", "CAR", "TRUCK", "BUS", "TRAILER", "MOTORCYCLE", "BICYCLE", "PEDESTRIAN",
          "ANIMAL", "HAZARD", "OVER_DRIVABLE", "UNDER_DRIVABLE")
#: Autoware label -> our models' class name; the labels not listed have no model class.
DEFAULT_CLASS_MAP = {"CAR": "car", "TRUCK": "truck", "PEDESTRIAN": "pedestrian",
                     "BICYCLE": "cyclist"}
BOUNDING_BOX, CYLINDER, POLYGON = 0, 1, 2


@dataclass
class AutowareOutput:
    """How a node writes DetectedObjects: its class map (None: :data:`DEFAULT_CLASS_MAP`)
    and ``existence_fallback`` (< 0: the node's own fallback, see the parameter)."""

    class_map: dict | None = None
    existence_fallback: float = -1.0


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


def _size(shape_type: int, dims, footprint) -> tuple[float, float, float]:
    if shape_type == BOUNDING_BOX:
        return dims[0], dims[1], dims[2]
    if shape_type == CYLINDER:
        return dims[0], dims[0], dims[2]
    if shape_type == POLYGON and footprint is not None and len(footprint):
        fp = np.asarray(footprint, np.float64)
        return (fp[:, 0].max() - fp[:, 0].min(), fp[:, 1].max() - fp[:, 1].min(), dims[2])
    return np.nan, np.nan, np.nan


def arrays_of_objects(pose, types, dims, footprints: dict, hyp_det, hyp_cls, hyp_score
                      ) -> DetectionArrays:
    """DetectionArrays from fields read out of DetectedObjects (of messages, or of their
    bytes: ``autoware_cdr``), so that both share one set of rules: ``pose`` (n, 7)
    position and quaternion x y z w, ``types`` (n,) shape types, ``dims`` (n, 3),
    ``footprints`` {object: (m, >= 2) points} of the polygons, one entry per
    classification (object, class name, probability)."""
    pose = np.asarray(pose, np.float64).reshape(-1, 7)
    dims = np.asarray(dims, np.float64).reshape(-1, 3)
    types = np.asarray(types, np.int64).reshape(-1)
    n = len(pose)
    size = np.array([_size(int(t), d, footprints.get(i)) for i, (t, d) in
                     enumerate(zip(types.tolist(), dims.tolist()))], np.float64).reshape(n, 3)
    raw = np.concatenate([pose[:, :3], size, pose[:, 3:7]], axis=1)
    arrays = arrays_from_fields(raw, [str(i) for i in range(n)], hyp_det, hyp_cls, hyp_score)
    for i in np.flatnonzero(~np.isin(types, (BOUNDING_BOX, CYLINDER, POLYGON))).tolist():
        arrays.reasons[i] = f"unknown shape type {types[i]}"  # in words, not as a NaN size
        arrays.valid[i] = False
    for i in np.flatnonzero(types == POLYGON).tolist():
        if footprints.get(i) is None or not len(footprints[i]):
            arrays.reasons[i] = "polygon shape without footprint points"
            arrays.valid[i] = False
    return arrays


def objects_to_arrays(msg, class_map: dict[str, str] | None = None) -> DetectionArrays:
    """``DetectionArrays`` of a DetectedObjects message (module docstring)."""
    names = label_names(class_map)
    pose, types, dims, footprints = [], [], [], {}
    hyp_det, hyp_cls, hyp_sc = [], [], []
    for i, obj in enumerate(msg.objects):
        pp = obj.kinematics.pose_with_covariance.pose
        p, q, d = pp.position, pp.orientation, obj.shape.dimensions
        pose.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
        types.append(obj.shape.type)
        dims.append((d.x, d.y, d.z))
        if obj.shape.type == POLYGON:
            footprints[i] = [(pt.x, pt.y) for pt in obj.shape.footprint.points]
        for c in obj.classification:
            hyp_det.append(i)
            hyp_cls.append(names[c.label] if c.label < len(names) else f"label_{c.label}")
            hyp_sc.append(c.probability)
    return arrays_of_objects(pose, types, dims, footprints, hyp_det, hyp_cls, hyp_sc)


def scored_values(existence, probs, det, confidence, fallback: float | None = None):
    """``(existence, probabilities, n_fallback)`` re-scored by ``confidence`` (one per
    object; ``probs`` flat with ``det`` its object): the confidence where finite, with the
    probabilities scaled as ``detection_cdr.rescaled_scores`` does; elsewhere the object's
    own existence (0 if not finite) or ``fallback``, the probabilities as they are."""
    conf = np.asarray(confidence, np.float64).reshape(-1)
    ex = np.asarray(existence, np.float64).reshape(-1)
    if len(conf) != len(ex):
        raise ValueError(f"{len(conf)} confidences for {len(ex)} objects")
    probs = np.asarray(probs, np.float64).reshape(-1)
    det = np.asarray(det, np.int64).reshape(-1)
    bad = ~np.isfinite(conf)
    own = np.where(np.isfinite(ex), ex, 0.0) if fallback is None else np.full(len(ex), fallback)
    new_ex = np.where(bad, own, conf)
    new_p = probs.copy()
    if len(det):
        scaled = rescaled_scores(probs, det, conf)
        ok = ~bad[det]
        new_p[ok] = scaled[ok]
    return new_ex, new_p, int(bad.sum())


def score_objects(msg, confidence, *, fallback: float | None = None) -> int:
    """Write ``confidence`` (one per object, NaN allowed) into ``msg`` in place (module
    docstring); returns how many objects got the fallback instead (NaN confidence)."""
    objects = msg.objects
    det = [i for i, o in enumerate(objects) for _ in o.classification]
    probs = [c.probability for o in objects for c in o.classification]
    ex, new_p, n_fallback = scored_values([o.existence_probability for o in objects], probs,
                                          det, confidence, fallback)
    it = iter(new_p.tolist())
    for obj, e in zip(objects, ex.tolist()):
        obj.existence_probability = e
        for cls in obj.classification:
            cls.probability = next(it)
    return n_fallback


def kept_objects(msg, kept):
    """``msg`` with only the objects where ``kept`` is True (same order; in place)."""
    msg.objects = [o for o, k in zip(msg.objects, np.asarray(kept, bool).tolist()) if k]
    return msg


def _label_of(class_map: dict[str, str] | None) -> dict[str, int]:
    """Our class name -> Autoware label value (the first label mapped to it)."""
    m = DEFAULT_CLASS_MAP if class_map is None else class_map
    out: dict[str, int] = {}
    for label, name in m.items():
        out.setdefault(name, LABELS.index(label))
    return out


def objects_from_boxes(header, boxes, class_names, class_probs, existence, *,
                       fallback=None, variance=None, class_map: dict[str, str] | None = None):
    """``(DetectedObjects, n_fallback)`` of new boxes (mimo_node's merged detections).

    ``boxes`` (n, 7) x y z l w h yaw; ``class_probs`` (n, C) over ``class_names``: one
    ObjectClassification per class, highest first (a class without an Autoware label:
    UNKNOWN); ``existence`` (n,) the meta confidence, NaN replaced by ``fallback[i]`` (or 0)
    and counted; ``variance`` (n, 4) of x, y, z, yaw on the pose covariance diagonal
    (``has_position_covariance`` where x, y, z are finite). Shape BOUNDING_BOX; the yaw's
    front / back is not established: ``orientation_availability`` SIGN_UNKNOWN.
    """
    from autoware_perception_msgs.msg import (DetectedObject, DetectedObjectKinematics,
                                              DetectedObjects, ObjectClassification)

    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    probs = np.asarray(class_probs, np.float64).reshape(len(boxes), len(class_names))
    ex = np.asarray(existence, np.float64).reshape(-1)
    fb = np.zeros(len(boxes)) if fallback is None else np.asarray(fallback, np.float64)
    bad = ~np.isfinite(ex)
    ex = np.where(bad, np.where(np.isfinite(fb), fb, 0.0), ex)
    labels = _label_of(class_map)
    codes = [labels.get(n, 0) for n in class_names]
    order = np.argsort(-np.nan_to_num(probs, nan=-np.inf), axis=1, kind="stable")
    quats = yaw_to_quaternion(boxes[:, 6]).tolist() if len(boxes) else []
    var = None if variance is None else np.asarray(variance, np.float64).reshape(-1, 4)
    out = DetectedObjects(header=header)
    for i, (b, q, e) in enumerate(zip(boxes.tolist(), quats, ex.tolist())):
        o = DetectedObject(existence_probability=e)
        o.classification = [ObjectClassification(label=codes[c], probability=probs[i, c])
                            for c in order[i].tolist()]
        k = o.kinematics
        pose = k.pose_with_covariance.pose
        pose.position.x, pose.position.y, pose.position.z = b[:3]
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q
        k.orientation_availability = DetectedObjectKinematics.SIGN_UNKNOWN
        if var is not None:
            cov = np.zeros(36)
            cov[[0, 7, 14, 35]] = var[i]
            k.pose_with_covariance.covariance = cov
            k.has_position_covariance = bool(np.isfinite(var[i, :3]).all())
        o.shape.type = BOUNDING_BOX
        o.shape.dimensions.x, o.shape.dimensions.y, o.shape.dimensions.z = b[3:6]
        out.objects.append(o)
    return out, int(bad.sum())


def objects_from_detections(msg, class_map: dict[str, str] | None = None):
    """DetectedObjects of a vision_msgs Detection3DArray, as an Autoware detector would
    publish the same detections: same header and order, pose = bbox centre (covariance
    unknown), BOUNDING_BOX of the bbox size, one classification per hypothesis (class
    names to labels by ``class_map``, UNKNOWN without one), ``existence_probability`` = the
    top hypothesis score. Ids are dropped (DetectedObject has none); scores become float32."""
    from autoware_perception_msgs.msg import (DetectedObject, DetectedObjectKinematics,
                                              DetectedObjects, ObjectClassification)

    labels = _label_of(class_map)
    out = DetectedObjects(header=msg.header)
    for d in msg.detections:
        hyps = [r.hypothesis for r in d.results]
        top = max((h.score for h in hyps), default=0.0)
        o = DetectedObject(existence_probability=float(top) if np.isfinite(top) else 0.0)
        o.kinematics.pose_with_covariance.pose = d.bbox.center
        o.kinematics.orientation_availability = DetectedObjectKinematics.SIGN_UNKNOWN
        o.shape.type = BOUNDING_BOX
        o.shape.dimensions = d.bbox.size
        o.classification = [ObjectClassification(label=labels.get(h.class_id, 0),
                                                 probability=h.score) for h in hyps]
        out.objects.append(o)
    return out


def input_type_param(inputs: str, vision_output: str):
    """The ``input_type`` parameter field of the nodes that read detections."""
    return param(
        "vision_msgs", f"Message type of {inputs} and of the scored output: 'vision_msgs' "
        f"(Detection3DArray in, {vision_output} out) or 'autoware' (autoware_perception_msgs/"
        "DetectedObjects in, output/objects out with the meta confidence as "
        "existence_probability).", choices=("vision_msgs", "autoware"))


def class_map_param():
    """The ``autoware_class_map`` parameter field."""
    return param(
        " ".join(f"{k}:{v}" for k, v in DEFAULT_CLASS_MAP.items()),
        "input_type autoware: Autoware classification label -> model class name "
        "('LABEL:name', separated by spaces or commas); an object whose top label is not "
        "mapped to one of class_names is not scored (counted as detections.invalid).")


def existence_fallback_param(own: str):
    """The ``existence_fallback`` parameter field; ``own``: what -1 keeps."""
    return param(
        -1.0, "input_type autoware: existence_probability of an object without a meta "
        f"confidence: -1 keeps {own} (0 if it is not finite), else this value. Counted as "
        "detections.fallback; NaN never goes out.", min_value=-1.0, max_value=1.0)
