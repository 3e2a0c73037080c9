"""Shared pytest configuration: the ROS harness fixture ``ros`` from lidar_quality_ros."""
pytest_plugins = ["lidar_quality_ros.testing"]
