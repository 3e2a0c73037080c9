"""Shared fixtures of the reference perception tests: one simulated frame and its cloud."""
import pytest
from sim_clouds import frame_cloud


@pytest.fixture(scope="session")
def sim_frame():
    from lidar_sim.frames import sequence_frames

    return next(sequence_frames(4242, 1))


@pytest.fixture(scope="session")
def sim_cloud(sim_frame):
    return frame_cloud(sim_frame)
