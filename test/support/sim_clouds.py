"""Simulated frames as PointCloud2 messages, for node tests."""
import numpy as np
from lidar_quality_core.pointcloud import create_cloud
from std_msgs.msg import Header


def frame_cloud(frame, sec: int = 7, frame_id: str = "lidar"):
    """The frame's sensor cloud: x, y, z, intensity (float32), ring (uint16)."""
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, 500
    return create_cloud(h, {"x": frame.xyz[:, 0], "y": frame.xyz[:, 1], "z": frame.xyz[:, 2],
                            "intensity": frame.intensity.astype(np.float32),
                            "ring": frame.ring.astype(np.uint16)})
