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

    def finite_points(self):
        """``(xyz, intensity, ring)`` of the points with finite coordinates."""
        return finite_points(self.xyz, self.intensity, self.ring, self.finite)


def finite_points(xyz, intensity, ring=None, finite=None):
    """``(xyz, intensity, ring)`` restricted to the points with finite coordinates."""
    ok = finite_mask(xyz) if finite is None else finite
    return xyz[ok], intensity[ok], None if ring is None else ring[ok]


def read_cloud(msg) -> CloudInput:
    """Decode a PointCloud2 (raises CloudFormatError on a malformed one)."""
    xyz, inten = xyz_intensity(msg)  # float32 (N, 3) and (N,) or None
    arr = cloud_to_structured(msg)
    ring_name = next((n for n in RING_FIELDS if n in (arr.dtype.names or ())), None)
    ring = None if ring_name is None else np.asarray(arr[ring_name]).reshape(-1).astype(np.int64)
    if ring is not None and len(ring) != len(xyz):
        raise CloudFormatError(f"field {ring_name!r} has a count other than 1")
    has_i = inten is not None
    inten = np.zeros(len(xyz), np.float32) if inten is None else inten
    return CloudInput(xyz=xyz, intensity=np.nan_to_num(inten, nan=0.0, posinf=0.0, neginf=0.0),
                      ring=ring, finite=finite_mask(xyz), has_intensity=has_i)
