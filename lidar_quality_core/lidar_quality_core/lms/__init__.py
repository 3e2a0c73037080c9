"""LidarMetaSeg core: range-image projection, segments, segment metrics and targets."""
