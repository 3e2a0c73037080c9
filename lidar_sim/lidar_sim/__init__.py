"""Synthetic lidar world: procedural street scenes, a ray-casting rotating lidar, exact
ground truth (no rclpy; numpy only)."""
