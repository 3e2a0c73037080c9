"""rclpy helpers shared by the lidar quality nodes (the computation lives in lidar_quality_core)."""
