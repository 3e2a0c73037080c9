"""ROS messages of the reference perception's outputs (message types only, no rclpy).

Conventions, shared by the nodes and the offline perception bag:

- Detections (post-NMS, proposals, heads): ``vision_msgs/Detection3DArray``, one
  ``results`` hypothesis per foreground class (``class_id`` = class name, ``score`` = its
  probability), highest first; the background probability is ``1 - sum(scores)``. Proposal
  ``id`` = its index in the frame's proposal array; a post-NMS detection keeps the ``id``
  of the proposal it came from, so the NMS pre-image of a detection is recoverable.
- x / y / z / yaw variances of a head's boxes on the pose covariance diagonal of every
  hypothesis (roll / pitch: 0); all seven box variances in a ``BoxVarianceArray``.
- Segmentation: a PointCloud2 with x, y, z, intensity (float32) and one probability field
  per class named :func:`probability_field` (float32, or uint8 = round(p * 255)).
"""
from __future__ import annotations

import numpy as np
from lidar_quality_core.boxes import arrays_to_detections
from lidar_quality_core.conventions import probability_field
from lidar_quality_core.pointcloud import create_cloud


def detection_array(header, boxes: np.ndarray, class_probs: np.ndarray, class_names, ids=None,
                    variances: np.ndarray | None = None):
    """Detection3DArray of boxes (N, 7) with foreground class probabilities (N, K)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    probs = np.asarray(class_probs, dtype=np.float64).reshape(len(boxes), len(class_names))
    cov = None
    if variances is not None:
        v = np.asarray(variances, dtype=np.float64).reshape(len(boxes), 7)
        cov = np.zeros((len(boxes), 6))
        cov[:, :3], cov[:, 5] = v[:, :3], v[:, 6]
    return arrays_to_detections(
        header, boxes, None, None, ids=list(range(len(boxes))) if ids is None else ids,
        class_scores={n: probs[:, k] for k, n in enumerate(class_names)},
        covariance_diagonal=cov)


def box_variance_array(header, variances: np.ndarray, ids=None):
    """BoxVarianceArray of (N, 7) variances (x, y, z, l, w, h, yaw)."""
    from lidar_quality_msgs.msg import BoxVariance, BoxVarianceArray

    v = np.asarray(variances, dtype=np.float64).reshape(-1, 7)
    ids = list(range(len(v))) if ids is None else ids
    return BoxVarianceArray(header=header, variances=[
        BoxVariance(detection_index=i, detection_id=str(ids[i]), x=r[0], y=r[1], z=r[2],
                    length=r[3], width=r[4], height=r[5], yaw=r[6])
        for i, r in enumerate(v.tolist())])


#: The reference perception's probability fields by default: uint8 (round(p * 255)), a
#: quarter of float32's bytes; the demo's LMS estimates with the shipped (float-trained)
#: models: AUROC unchanged, ECE +0.004, R² -0.007 (README "Benchmarks").
QUANTIZE_DEFAULT = True


def probability_cloud(header, xyz: np.ndarray, intensity: np.ndarray, probs: np.ndarray,
                      class_names, *, quantize: bool = False):
    """PointCloud2: the points plus one probability field per class (see module doc)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    probs = np.asarray(probs).reshape(len(xyz), len(class_names))
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
            "intensity": np.asarray(intensity, dtype=np.float32)}
    p = (np.rint(np.clip(probs, 0, 1) * 255).astype(np.uint8) if quantize
         else probs.astype(np.float32, copy=False))
    for k, name in enumerate(class_names):
        cols[probability_field(name)] = p[:, k]
    return create_cloud(header, cols)


def detector_messages(header, out, class_names):
    """(detections, proposals) Detection3DArrays of a DetectorOutput whose class
    distribution columns are background + ``class_names``."""
    fg = out.class_probs[:, 1:]
    dets = detection_array(header, out.boxes[out.keep], fg[out.keep], class_names,
                           ids=out.keep.tolist())
    return dets, detection_array(header, out.boxes, fg, class_names)


def head_messages(header, out, class_names):
    """[(Detection3DArray, BoxVarianceArray)] per head of a MultiHeadOutput."""
    msgs = []
    for h in out.heads:
        ids = h.keep.tolist()
        msgs.append((detection_array(header, h.boxes[h.keep], h.class_probs[h.keep, 1:],
                                     class_names, ids=ids, variances=h.variances[h.keep]),
                     box_variance_array(header, h.variances[h.keep], ids=ids)))
    return msgs
