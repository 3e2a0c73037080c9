"""Shared pytest configuration: the ROS harness fixture ``ros`` from lidar_quality_ros."""
pytest_plugins = ["lidar_quality_ros.testing"]

import sys
from pathlib import Path

# Helpers shared by several test modules (plain functions, not fixtures).
sys.path.insert(0, str(Path(__file__).parent / "support"))
