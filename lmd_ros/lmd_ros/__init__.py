"""LidarMetaDetect: box-wise meta confidence and predicted IoU for lidar 3D detections."""
