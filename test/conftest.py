"""Shared pytest configuration: the ROS harness fixture ``ros`` from lidar_quality_ros."""
import sys
from pathlib import Path

pytest_plugins = ["lidar_quality_ros.testing"]

# Helpers shared by several test modules (plain functions, not fixtures).
sys.path.insert(0, str(Path(__file__).parent / "support"))
