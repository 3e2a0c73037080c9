"""Tests of reference_perception.proposals (the detector front end)."""
import json

import numpy as np
from car_scene import GROUND_Z, car_scene
from lidar_quality_core.iou import iou_bev
from reference_perception.box_fit import METHODS
from reference_perception.proposals import FEATURE_NAMES, FrontEndConfig, compute_proposals


def test_candidates_of_a_simple_scene():
    sc, gt = car_scene(12.0, 3.0, 0.3)
    p = compute_proposals(sc.xyz, sc.intensity, sc.ring)
    assert p.features.shape == (len(p), len(FEATURE_NAMES)) and p.features.dtype == np.float32
    assert np.isfinite(p.features).all() and np.isfinite(p.boxes).all()
    # every method per cluster, the line-of-sight one only for sparse clusters
    n_fits = np.bincount(p.cluster, minlength=len(p.clusters))
    dense = p.clusters.sizes >= FrontEndConfig().sight_max_points
    np.testing.assert_array_equal(n_fits, np.where(dense, len(METHODS) - 1, len(METHODS)))
    # several fits of the car's cluster(s) overlap its box
    iou = iou_bev(p.boxes, gt)[:, 0]
    assert (iou > 0.5).sum() >= 3
    # the car, the pole and the bush: a handful of clusters, not hundreds
    assert 3 <= len(p.clusters) <= 20
    # clusters hold no ground points
    assert not p.ground.is_ground[p.clusters.point_index].any()
    car_pts = np.flatnonzero(sc.instance == 1)
    best = p.cluster[np.argmax(iou)]
    assert np.isin(p.clusters.members(best), car_pts).mean() > 0.95
    f = dict(zip(FEATURE_NAMES, p.features[np.argmax(iou)]))
    assert f["n_points"] > 200 and 10 < f["range"] < 14 and 1.2 < f["height_max"] < 1.8


def test_shared_ground_and_config_round_trip():
    sc, _ = car_scene(-8.0, -6.0, 1.0, seed=1)
    cfg = FrontEndConfig()
    again = FrontEndConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert again == cfg
    a = compute_proposals(sc.xyz, sc.intensity, None, cfg)
    b = compute_proposals(sc.xyz, sc.intensity, None, again, ground=a.ground)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.features, b.features)
    assert set(a.timings_ms) == {"ground", "cluster", "box_fit", "features"}


def test_empty_and_ground_only_clouds():
    for xyz in (np.zeros((0, 3), np.float32),
                np.c_[np.random.default_rng(0).uniform(-30, 30, (5000, 2)),
                      np.full(5000, GROUND_Z)].astype(np.float32)):
        p = compute_proposals(xyz, np.zeros(len(xyz), np.float32))
        assert len(p) == 0 and p.features.shape == (0, len(FEATURE_NAMES))
        assert p.boxes.shape == (0, 7)
