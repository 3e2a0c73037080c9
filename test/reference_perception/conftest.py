"""Shared fixtures of the reference perception tests: one simulated frame as a cloud."""
import numpy as np
import pytest
from lidar_quality_core.pointcloud import create_cloud
from std_msgs.msg import Header


@pytest.fixture(scope="session")
def sim_frame():
    from lidar_sim.frames import sequence_frames

    return next(sequence_frames(4242, 1))


def frame_cloud(frame, sec: int = 7, frame_id: str = "lidar"):
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, 500
    return create_cloud(h, {"x": frame.xyz[:, 0], "y": frame.xyz[:, 1], "z": frame.xyz[:, 2],
                            "intensity": frame.intensity.astype(np.float32),
                            "ring": frame.ring.astype(np.uint16)})


@pytest.fixture(scope="session")
def sim_cloud(sim_frame):
    return frame_cloud(sim_frame)
