"""LidarMetaSeg targets (IoU, IoU_adj) on hand-built range images; the random-cloud
comparison with the brute-force definitions is in test_segment_metrics."""
import numpy as np
import pytest

from lidar_quality_core.lms.projection import RangeImageConfig
from lidar_quality_core.lms.segment_metrics import compute_segments
from lidar_quality_core.lms.targets import segment_targets
from lms_images import image_cloud


def test_iou_adj_one_ground_truth_segment_two_predicted_segments():
    # ground truth: class 1 on row 2, cols 1..10 (10 pixels). Prediction: class 1 on
    # cols 1..4 and 6..10, class 0 at col 5 (splits the ground-truth segment in two)
    cfg = RangeImageConfig.uniform(5, 14, 10.0, -20.0)
    pred = np.zeros((5, 14), int)
    pred[2, 1:5] = 1
    pred[2, 6:11] = 1
    gt_img = np.zeros((5, 14), int)
    gt_img[2, 1:11] = 1
    xyz, probs, n = image_cloud(cfg, pred)
    gt = gt_img[pred >= 0]
    res = compute_segments(xyz, probs, cfg, min_points=1)
    iou, adj = segment_targets(res, gt)
    a, b = res.segments[2, 1], res.segments[2, 6]
    ka, kb = (np.flatnonzero(res.kept_ids == s)[0] for s in (a, b))
    assert iou[ka] == pytest.approx(4 / 10) and iou[kb] == pytest.approx(5 / 10)
    # IoU_adj: the other predicted segment's pixels do not count; col 5 (missed) does
    assert adj[ka] == pytest.approx(4 / 5) and adj[kb] == pytest.approx(5 / 6)
    # the class-0 segment: GT class 0 everywhere except row 2 cols 1..10; it contains
    # (2, 5) predicted 0 whose GT is 1
    c0 = np.flatnonzero(res.segment_class[res.kept_ids] == 0)
    assert len(c0) == 1
    n0 = (pred == 0).sum()
    assert iou[c0[0]] == pytest.approx((n0 - 1) / (n0 + 0)) and adj[c0[0]] == iou[c0[0]]
    # a false positive: predicted class 1 where the ground truth has none
    gt2 = np.zeros_like(gt)
    iou2, adj2 = segment_targets(res, gt2)
    assert iou2[ka] == 0.0 and adj2[ka] == 0.0


def test_targets_count_projected_pixels_only_and_ignore_label():
    cfg = RangeImageConfig.uniform(3, 8, 10.0, -20.0)
    pred = np.zeros((3, 8), int)
    pred[1, 2:6] = 1
    pred[1, 3] = -1                    # an empty pixel inside the segment: filled, not counted
    xyz, probs, n = image_cloud(cfg, pred)
    gt = np.ones(len(xyz), int)        # GT: class 1 everywhere
    res = compute_segments(xyz, probs, cfg, min_points=1)
    assert res.size[res.segments[1, 2]] == 4 and res.size_projected[res.segments[1, 2]] == 3
    iou, adj = segment_targets(res, gt, kept_only=False)
    s = res.segments[1, 2]
    assert iou[s] == pytest.approx(3 / 23)       # 23 projected pixels of GT class 1
    assert adj[s] == pytest.approx(3 / 23)       # the rest is predicted 0: no other seg of 1
    # GT ignored on 20 of the points: they count nowhere
    gt_ign = gt.copy()
    gt_ign[pred[pred >= 0] == 0] = 255
    iou, adj = segment_targets(res, gt_ign, ignore_label=255, kept_only=False)
    assert iou[s] == 1.0 and adj[s] == 1.0
    assert np.isnan(iou[res.segments[0, 0]])     # nothing counted: 0 / 0
    with pytest.raises(ValueError, match="outside"):
        segment_targets(res, gt_ign)
    with pytest.raises(ValueError, match="entries"):
        segment_targets(res, gt[:-1])
