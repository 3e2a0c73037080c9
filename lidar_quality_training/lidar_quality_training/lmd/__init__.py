"""LidarMetaDetect (LMD) meta models: dataset builder, training and evaluation command lines."""
