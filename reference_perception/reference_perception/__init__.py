"""Reference lidar perception learned on simulated scans (no rclpy outside ``*_node``)."""
