"""LidarMetaSeg: segment-wise false-positive probability and predicted IoU for lidar segmentation."""
