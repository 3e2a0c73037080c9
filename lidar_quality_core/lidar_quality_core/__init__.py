"""Shared computation core of the lidar quality suite (numpy / scipy only, no rclpy).

Modules: ``pointcloud`` (PointCloud2 <-> numpy), ``boxes`` (Detection3D <-> arrays),
``box_geometry`` (corners, points in boxes), ``iou`` (rotated BEV / 3D IoU), ``nms``
(rotated NMS), ``time_sync`` (stamp synchronisation), ``model_store`` (verified meta
model loading), ``metrics`` (meta task metrics), ``synthetic`` (synthetic frames).
"""
