"""The reference nodes' view of an input cloud: finite points, intensity, optional ring."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from lidar_quality_core.pointcloud import CloudFormatError, cloud_to_structured, finite_mask, xyz_intensity

RING_FIELDS = ("ring", "channel", "laser_id")


@dataclass
class CloudInput:
    xyz: np.ndarray                 # (N, 3) float32, all points of the message
    intensity: np.ndarray           # (N,) float32 (zeros when the cloud has none)
    ring: np.ndarray | None         # (N,) int, or None
    finite: np.ndarray              # (N,) bool
    has_intensity: bool


def read_cloud(msg) -> CloudInput:
    """Decode a PointCloud2 (raises CloudFormatError on a malformed one)."""
    xyz, inten = xyz_intensity(msg)
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    names = cloud_to_structured(msg).dtype.names or ()
    ring = None
    for name in RING_FIELDS:
        if name in names:
            ring = np.asarray(cloud_to_structured(msg)[name]).reshape(-1).astype(np.int64)
            break
    has_i = inten is not None
    inten = np.zeros(len(xyz), np.float32) if inten is None else np.asarray(inten, np.float32).reshape(-1)
    if len(inten) != len(xyz):
        raise CloudFormatError("intensity and xyz lengths differ")
    return CloudInput(xyz=xyz, intensity=np.nan_to_num(inten, nan=0.0, posinf=0.0, neginf=0.0),
                      ring=ring, finite=finite_mask(xyz), has_intensity=has_i)
