"""Tests for lidar_quality_core.mimo.clustering (voting rules, neighbour pairs, DBSCAN)."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.cluster import DBSCAN

from lidar_quality_core.iou import sparse_iou
from lidar_quality_core.mimo.clustering import (dbscan_pairs, dbscan_sklearn, min_cluster_size,
                                                neighbour_pairs)

CAR = np.array([10.0, 5.0, -1.0, 4.5, 1.9, 1.6, 0.3])
PED = np.array([10.5, 5.0, -1.0, 0.8, 0.7, 1.7, 0.0])  # inside the car's footprint


# ------------------------------------------------------------------ voting rules
@pytest.mark.parametrize("K, rules", [(1, (1, 1, 1)), (2, (1, 2, 2)), (3, (1, 2, 3)),
                                      (4, (1, 3, 4)), (5, (1, 3, 5))])
def test_min_cluster_size(K, rules):
    assert tuple(min_cluster_size(v, K) for v in ("affirmative", "consensus", "unanimous")) == rules


# ------------------------------------------------------------------ DBSCAN and pairs
def _sk(n, i, j, ms):
    d = np.ones((n, n))
    np.fill_diagonal(d, 0.0)
    d[i, j] = d[j, i] = 0.0
    return DBSCAN(eps=0.5, min_samples=ms, metric="precomputed").fit_predict(d)


def test_dbscan_border_point_goes_to_the_first_cluster():
    # cores 0-1 and 3-4 (min 2 with a chain), point 2 touches both as a border point
    # with min_samples 3: 0, 1 ... build: 0-1, 1-2, 2-3, 3-4, and 0-5, 4-6
    i = np.array([0, 1, 2, 3, 0, 4, 1])
    j = np.array([1, 2, 3, 4, 5, 6, 5])
    for ms in (1, 2, 3, 4):
        np.testing.assert_array_equal(dbscan_pairs(7, i, j, ms), _sk(7, i, j, ms))


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 25), st.integers(1, 5), st.integers(0, 2**31 - 1), st.floats(0.02, 0.4))
def test_own_dbscan_equals_sklearn(n, ms, seed, density):
    rng = np.random.default_rng(seed)
    iu, ju = np.triu_indices(n, 1)
    keep = rng.random(len(iu)) < density
    i, j = iu[keep], ju[keep]
    perm = rng.permutation(len(i))  # pair order must not matter
    np.testing.assert_array_equal(dbscan_pairs(n, i[perm], j[perm], ms), _sk(n, i, j, ms))
    np.testing.assert_array_equal(dbscan_sklearn(n, i, j, ms), _sk(n, i, j, ms))


@pytest.mark.parametrize("ms", [1, 2, 3])
def test_own_dbscan_equals_sklearn_on_long_chains(ms):
    # components whose roots are reached late (pairs listed from the far end), as a
    # union-find must get right: long chains, a star, pairs in reverse order
    rng = np.random.default_rng(7)
    n = 400
    order = rng.permutation(n)
    chain = np.sort(np.column_stack([order[:-1], order[1:]]), axis=1)[::-1]
    i, j = chain[:, 0], chain[:, 1]
    cut = rng.random(len(i)) < 0.05  # ~20 chains
    i, j = np.append(i[~cut], np.zeros(5, int)), np.append(j[~cut], np.arange(395, 400))
    np.testing.assert_array_equal(dbscan_pairs(n, i, j, ms), _sk(n, i, j, ms))


def test_own_dbscan_refuses_pairs_outside_the_points():
    with pytest.raises(ValueError, match="outside 0..2"):
        dbscan_pairs(3, np.array([0]), np.array([3]), 1)
    with pytest.raises(ValueError, match="outside"):
        dbscan_pairs(0, np.array([0]), np.array([1]), 1)
    assert dbscan_pairs(0, np.zeros(0, int), np.zeros(0, int), 2).shape == (0,)


def _ref_pairs(boxes, eps, labels=None):
    i, j, v = sparse_iou(boxes)
    k = (1.0 - v) <= eps
    if labels is not None:
        k &= labels[i] == labels[j]
    return set(zip(i[k].tolist(), j[k].tolist()))


@settings(max_examples=150, deadline=None)
@given(st.integers(2, 30), st.integers(0, 2**31 - 1), st.sampled_from([0.2, 0.5, 0.7, 0.9]),
       st.sampled_from(["free", "square", "aligned", "near45", "copies"]))
def test_neighbour_pairs_equal_thresholded_sparse_iou(n, seed, eps, kind):
    rng = np.random.default_rng(seed)
    b = np.column_stack([rng.uniform(0, 5, (n, 2)), np.zeros(n), rng.uniform(0.3, 4, (n, 2)),
                         np.ones(n), rng.uniform(-4, 4, n)])
    if kind == "square":
        b[:, 4] = b[:, 3]
    elif kind == "aligned":
        b[:, 6] = rng.choice([0.0, math.pi / 2, math.pi, -math.pi], n)
    elif kind == "near45":
        b[:, 6] = rng.choice([0.0, math.pi / 4 + 1e-9, -math.pi / 4], n)
    elif kind == "copies":  # jittered copies: IoU near every threshold
        jitter = rng.normal(0, 0.15, (n - n // 2, 7)) * [1, 1, 0, 0.3, 0.3, 0, 0.3]
        b[n // 2:] = b[: n - n // 2] + jitter
        b[:, 3:5] = np.abs(b[:, 3:5]) + 0.05
    labels = rng.integers(0, 2, n)
    i, j = neighbour_pairs(b, eps)
    assert np.all(i < j)
    assert set(zip(i.tolist(), j.tolist())) == _ref_pairs(b, eps)
    i, j = neighbour_pairs(b, eps, labels)
    assert set(zip(i.tolist(), j.tolist())) == _ref_pairs(b, eps, labels)
    b.flags.writeable = False  # e.g. a view of a message: the same pairs, in the same order
    i2, j2 = neighbour_pairs(b, eps, labels)
    assert i2.tolist() == i.tolist() and j2.tolist() == j.tolist()


def test_neighbour_pairs_identical_and_invalid_boxes():
    b = np.stack([CAR, CAR, CAR, PED])
    b[2, 3] = 0.0
    assert set(zip(*map(list, neighbour_pairs(b, 0.5)))) == {(0, 1)}
    assert len(neighbour_pairs(b[:1], 0.5)[0]) == 0
