"""LiDAR-MIMO: merge the heads of a multi-output 3D detector, uncertainty and meta quality."""
