"""Tests of reference_perception.clustering (multi-scale BEV connected components)."""
import numpy as np
import pytest

from reference_perception.clustering import (ClusterConfig, Clusters, candidate_mask,
                                             cluster_points)


def blob(rng, cx, cy, n=200, sx=0.8, sy=0.4, z=-1.0):
    return np.c_[rng.uniform(cx - sx, cx + sx, n), rng.uniform(cy - sy, cy + sy, n),
                 np.full(n, z)].astype(np.float32)


def sets(cl: Clusters):
    return [frozenset(cl.members(c).tolist()) for c in range(len(cl))]


def test_isolated_blobs_are_one_cluster_each_at_every_scale():
    rng = np.random.default_rng(0)
    xyz = np.r_[blob(rng, 10, 0), blob(rng, -5, 8)]
    cfg = ClusterConfig()
    cl = cluster_points(xyz, np.ones(len(xyz), bool), cfg)
    # identical point sets of several scales are kept once, with their scale count
    assert len(cl) == 2
    assert set(sets(cl)) == {frozenset(range(200)), frozenset(range(200, 400))}
    np.testing.assert_array_equal(cl.n_scales, [len(cfg.cell_sizes)] * 2)
    np.testing.assert_array_equal(cl.scale, [0, 0])


def test_fine_scales_split_and_coarse_scales_merge():
    rng = np.random.default_rng(1)
    # two blobs with a 0.5 m gap: apart at 0.15 / 0.25 m cells, one cluster at 0.7 m cells
    a, b = blob(rng, 0.0, 20.0, sx=0.5), blob(rng, 1.5, 20.0, sx=0.5)
    xyz = np.r_[a, b]
    cl = cluster_points(xyz, np.ones(len(xyz), bool), ClusterConfig(cell_sizes=(0.15, 0.7)))
    got = set(sets(cl))
    assert frozenset(range(200)) in got and frozenset(range(200, 400)) in got
    assert frozenset(range(400)) in got
    assert len(cl) == 3
    merged = sets(cl).index(frozenset(range(400)))
    assert cl.scale[merged] == 1 and cl.n_scales[merged] == 1


def test_csr_layout_and_filters():
    rng = np.random.default_rng(2)
    wall = np.c_[rng.uniform(0, 25, 2000), np.full(2000, 15.0), rng.uniform(-1.5, 1, 2000)]
    tiny = np.array([[30.0, -30.0, -1.0], [30.05, -30.0, -1.0]])     # below min_points
    xyz = np.r_[blob(rng, 10, -3), wall, tiny].astype(np.float32)
    cl = cluster_points(xyz, np.ones(len(xyz), bool), ClusterConfig(min_points=4,
                                                                     max_extent=13.0))
    assert len(cl) == 1                                   # the wall is too long, tiny too small
    assert cl.offsets[0] == 0 and cl.offsets[-1] == len(cl.point_index)
    for c in range(len(cl)):
        m = cl.members(c)
        assert np.all(np.diff(m) > 0)                     # ascending, no repeats
    np.testing.assert_array_equal(cl.owner, np.repeat(np.arange(len(cl)), cl.sizes))


def test_candidate_mask():
    xyz = np.array([[5, 0, -1.0], [5, 0, -1.0], [5, 0, 5.0], [90, 0, -1.0], [5, 0, -1.6]],
                   np.float32)
    height = np.array([0.7, 0.7, 6.7, 0.7, 0.1], np.float32)
    ground = np.array([False, True, False, False, False])
    m = candidate_mask(xyz, height, ground, ClusterConfig(max_range=80.0))
    np.testing.assert_array_equal(m, [True, False, False, False, False])
    # NaN heights (non-finite points) are never candidates
    assert not candidate_mask(xyz[:1], np.array([np.nan], np.float32), ground[:1]).any()


def test_degenerate_inputs():
    xyz = np.zeros((0, 3), np.float32)
    cl = cluster_points(xyz, np.zeros(0, bool))
    assert len(cl) == 0 and cl.offsets.tolist() == [0]
    xyz = np.array([[1.0, 1.0, 0.0]] * 3, np.float32)
    assert len(cluster_points(xyz, np.ones(3, bool), ClusterConfig(min_points=4))) == 0
    # all points in one cell: one cluster
    cl = cluster_points(np.array([[1.0, 1.0, 0.0]] * 5, np.float32), np.ones(5, bool))
    assert len(cl) == 1 and cl.sizes.tolist() == [5]


@pytest.mark.parametrize("cfg", [ClusterConfig(), ClusterConfig(cell_sizes=(0.3,))])
def test_config_round_trip(cfg):
    assert ClusterConfig.from_dict(cfg.to_dict()) == cfg
