"""Tests for lidar_quality_core.synthetic (deterministic synthetic frames)."""
import dataclasses

import numpy as np
import pytest

from lidar_quality_core.box_geometry import count_points_in_boxes
from lidar_quality_core.iou import iou_bev, iou_bev_pairs
from lidar_quality_core.synthetic import SENSOR_HEIGHT, SyntheticFrame, synthetic_frame


@pytest.fixture(scope="module")
def frame():
    return synthetic_frame()


def test_default_shapes_and_dtypes(frame):
    assert frame.points.shape == (120_000, 3) and frame.points.dtype == np.float32
    assert frame.intensity.shape == (120_000,) and frame.intensity.dtype == np.float32
    assert frame.gt_boxes.shape == (50, 7)
    assert frame.detections.shape == (50, 7) and frame.det_scores.shape == (50,)
    assert frame.proposals.shape == (500, 7) and frame.prop_scores.shape == (500,)
    assert frame.gt_classes.shape == frame.det_classes.shape == (50,)
    assert frame.prop_classes.shape == frame.prop_object.shape == (500,)
    for f in dataclasses.fields(SyntheticFrame):
        assert np.all(np.isfinite(getattr(frame, f.name))), f.name


def test_deterministic_per_seed():
    a, b, c = synthetic_frame(5000, 8, 40, seed=1), synthetic_frame(5000, 8, 40, seed=1), \
        synthetic_frame(5000, 8, 40, seed=2)
    for f in dataclasses.fields(SyntheticFrame):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))
    assert not np.array_equal(a.points, c.points)
    assert not np.array_equal(a.gt_boxes, c.gt_boxes)


@pytest.mark.parametrize("n_points", [0, 1, 63, 64, 1000, 12_345])
def test_exact_point_count(n_points):
    f = synthetic_frame(n_points=n_points, n_objects=3, n_proposals=7)
    assert f.points.shape == (n_points, 3) and f.intensity.shape == (n_points,)


def test_scan_pattern_column_major():
    f = synthetic_frame(n_points=1000, n_objects=0, n_proposals=0)  # 15.6 columns -> 16
    az = np.arctan2(f.points[:, 1], f.points[:, 0])
    col = np.arange(1000) // 64
    expected = -np.pi + col * (2 * np.pi / 16)
    err = np.angle(np.exp(1j * (az - expected)))
    assert np.abs(err).max() < 0.1 * 2 * np.pi / 16
    ring_elev = np.arctan2(f.points[:64, 2], np.hypot(f.points[:64, 0], f.points[:64, 1]))
    assert np.all(np.diff(ring_elev) > 0)  # one column = 64 rings, bottom to top


def test_degenerate_counts():
    f = synthetic_frame(n_points=500, n_objects=0, n_proposals=10)
    assert f.gt_boxes.shape == (0, 7) and f.proposals.shape == (10, 7)
    assert (f.prop_object == -1).all()
    f = synthetic_frame(n_points=500, n_objects=4, n_proposals=0)
    assert f.proposals.shape == (0, 7) and f.detections.shape == (4, 7)


def test_value_ranges(frame):
    assert 0.0 <= frame.intensity.min() and frame.intensity.max() <= 1.0
    for s in (frame.det_scores, frame.prop_scores):
        assert (s > 0).all() and (s <= 1).all()
    gt = frame.gt_boxes
    assert (gt[:, 3:6] > 0.2).all() and (gt[:, 3] < 7).all() and (gt[:, 5] < 3).all()
    np.testing.assert_allclose(gt[:, 2] - gt[:, 5] / 2, -SENSOR_HEIGHT)  # standing on ground
    r = np.hypot(gt[:, 0], gt[:, 1])
    assert (r >= 5).all() and (r <= 60).all()
    # objects do not overlap each other
    m = iou_bev(gt, gt)
    np.fill_diagonal(m, 0)
    assert m.max() == 0
    rng_pts = np.hypot(frame.points[:, 0], frame.points[:, 1])
    assert rng_pts.max() < 130
    # most returns are ground hits around the sensor height below the origin
    assert np.mean(np.abs(frame.points[:, 2] + SENSOR_HEIGHT) < 0.1) > 0.5


def test_objects_are_hit_and_detections_are_close(frame):
    counts = count_points_in_boxes(frame.points, frame.gt_boxes, margin=0.05)
    assert (counts > 0).mean() > 0.8  # a few objects may be occluded
    assert counts.sum() > 3000
    assert np.median(iou_bev_pairs(frame.detections, frame.gt_boxes)) > 0.6
    np.testing.assert_array_equal(frame.det_classes, frame.gt_classes)


def test_proposals_cluster_around_objects(frame):
    src = frame.prop_object
    cl = src >= 0
    assert 0.8 < cl.mean() < 0.95
    assert len(np.unique(src[cl])) == 50  # every object gets proposals
    d = np.hypot(*(frame.proposals[cl, :2] - frame.gt_boxes[src[cl], :2]).T)
    assert np.median(d) < 1.0
    np.testing.assert_array_equal(frame.prop_classes[cl], frame.gt_classes[src[cl]])
    assert frame.prop_scores[cl].mean() > frame.prop_scores[~cl].mean()
