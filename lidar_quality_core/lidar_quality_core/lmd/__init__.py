"""LidarMetaDetect core: box-wise features from post-NMS boxes, in-box points and proposals."""
