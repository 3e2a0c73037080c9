"""LiDAR-MIMO core: clustering and merging of the heads' boxes, uncertainty, calibration, scoring rules."""
