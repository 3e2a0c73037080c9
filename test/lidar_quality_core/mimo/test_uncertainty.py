"""Tests for lidar_quality_core.mimo.uncertainty (LiDAR-MIMO cluster statistics)."""
import math

import numpy as np
import pytest

from lidar_quality_core.mimo.uncertainty import (classification_statistics, cluster_statistics,
                                                 entropy_bits, group_mean,
                                                 regression_statistics, wrap_angle)


def h2(p):
    return -sum(x * math.log2(x) for x in p if x > 0)


def test_entropy_bits():
    assert entropy_bits([0.25] * 4) == pytest.approx(2.0)
    assert entropy_bits([1.0, 0.0, 0.0]) == 0.0
    np.testing.assert_allclose(entropy_bits([[0.5, 0.5, 0.0], [0.9, 0.1, 0.0]]),
                               [1.0, h2([0.9, 0.1])])


def test_wrap_angle():
    np.testing.assert_allclose(wrap_angle([0.0, math.pi + 0.1, -math.pi - 0.1, 2 * math.pi]),
                               [0.0, -math.pi + 0.1, math.pi - 0.1, 0.0], atol=1e-12)


def test_group_mean():
    x = np.arange(10.0).reshape(5, 2)
    np.testing.assert_allclose(group_mean(x, np.array([0, 2]), np.array([2, 3])),
                               [[1.0, 2.0], [6.0, 7.0]])


def _stats(probs, boxes, var=None, starts=(0,), top=None, **kw):
    boxes = np.asarray(boxes, float)
    var = np.full(boxes.shape, np.nan) if var is None else np.asarray(var, float)
    starts = np.asarray(starts)
    return cluster_statistics(np.asarray(probs, float), boxes, var, starts,
                              starts if top is None else np.asarray(top), **kw)


def test_hand_computed_se_ae_mi():
    # members [0.5, 0.5] and [1, 0]: mean [0.75, 0.25]
    s = _stats([[0.5, 0.5], [1.0, 0.0]], np.zeros((2, 7)))
    se, ae = h2([0.75, 0.25]), (1.0 + 0.0) / 2
    assert s.shannon_entropy[0] == pytest.approx(se)            # 0.8113 bit
    assert s.aleatoric_entropy[0] == pytest.approx(ae)
    assert s.mutual_information[0] == pytest.approx(se - ae)    # 0.3113 bit
    # three classes, three members
    p = [[0.7, 0.2, 0.1], [0.2, 0.7, 0.1], [0.1, 0.1, 0.8]]
    s = _stats(p, np.zeros((3, 7)))
    mean = np.mean(p, axis=0)
    assert s.shannon_entropy[0] == pytest.approx(h2(mean))
    assert s.aleatoric_entropy[0] == pytest.approx(np.mean([h2(r) for r in p]))
    assert s.mutual_information[0] == pytest.approx(h2(mean) - np.mean([h2(r) for r in p]))


def test_identical_members_have_no_epistemic_uncertainty():
    p = [[0.1, 0.6, 0.3]] * 4
    b = [[10.0, -3.0, -1.0, 4.5, 1.9, 1.6, 0.7]] * 4
    v = [[0.1, 0.2, 0.05, 0.3, 0.1, 0.1, 0.02]] * 4
    s = _stats(p, b, v)
    assert s.mutual_information[0] == pytest.approx(0.0, abs=1e-12)
    assert s.epistemic_total_variance[0] == 0.0
    assert s.aleatoric_total_variance[0] == pytest.approx(0.87)
    np.testing.assert_allclose(s.predictive_variance[0], v[0])
    assert s.cluster_size[0] == 4


def test_known_offset_gives_known_etv():
    b0 = np.array([5.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.3])
    d = np.array([0.2, -0.4, 0.1, 0.3, 0.0, -0.2, 0.06])
    s = _stats([[0.2, 0.8]] * 2, [b0, b0 + d], [[0.1] * 7, [0.3] * 7])
    # population variance of two values a, a + d is (d / 2)^2
    np.testing.assert_allclose(s.epistemic_variance[0], (d / 2) ** 2, atol=1e-15)
    assert s.epistemic_total_variance[0] == pytest.approx(np.sum((d / 2) ** 2))
    np.testing.assert_allclose(s.aleatoric_variance[0], [0.2] * 7)
    assert s.aleatoric_total_variance[0] == pytest.approx(1.4)
    pred = (d / 2) ** 2 + 0.2
    pred[6] = 0.1  # yaw: the top member's predicted variance (top = first member)
    np.testing.assert_allclose(s.predictive_variance[0], pred)


def test_yaw_wrap_and_options():
    y = [math.pi - 0.01, -math.pi + 0.01]
    b = np.zeros((2, 7))
    b[:, 6] = y
    v = np.full((2, 7), 0.5)
    v[1, 6] = 0.9
    wrapped = _stats([[1.0, 0.0]] * 2, b, v)
    assert wrapped.epistemic_variance[0, 6] == pytest.approx(1e-4)
    raw = _stats([[1.0, 0.0]] * 2, b, v, yaw_deviation="raw")
    assert raw.epistemic_variance[0, 6] == pytest.approx(((y[0] - y[1]) / 2) ** 2)
    assert wrapped.predictive_variance[0, 6] == 0.5  # top member (row 0)
    top1 = _stats([[1.0, 0.0]] * 2, b, v, top=[1])
    assert top1.predictive_variance[0, 6] == 0.9
    mix = _stats([[1.0, 0.0]] * 2, b, v, yaw_variance="mixture")
    assert mix.predictive_variance[0, 6] == pytest.approx(1e-4 + 0.7)
    # a heading flip stays a large disagreement
    b[1, 6] = y[0] - math.pi
    assert _stats([[1.0, 0.0]] * 2, b).epistemic_variance[0, 6] == pytest.approx(math.pi ** 2 / 4)
    with pytest.raises(ValueError, match="yaw_deviation"):
        _stats([[1.0, 0.0]] * 2, b, yaw_deviation="circular")


def test_several_groups_at_once_and_unknown_variances():
    rng = np.random.default_rng(3)
    sizes = [1, 3, 2, 4]
    M = sum(sizes)
    p = rng.dirichlet(np.ones(5), M)
    b = rng.normal(0.0, 1.0, (M, 7))
    v = rng.uniform(0.1, 1.0, (M, 7))
    v[2, 2] = np.nan  # second group (rows 1-3): unknown z variance
    starts = np.cumsum([0] + sizes[:-1])
    top = starts + np.array([0, 2, 1, 3])
    s = cluster_statistics(p, b, v, starts, top, yaw_deviation="raw")
    for g, (st, n) in enumerate(zip(starts, sizes)):
        sl = slice(st, st + n)
        np.testing.assert_allclose(s.epistemic_variance[g], b[sl].var(axis=0), atol=1e-12)
        assert s.shannon_entropy[g] == pytest.approx(h2(p[sl].mean(axis=0)))
        assert s.aleatoric_entropy[g] == pytest.approx(np.mean([h2(r) for r in p[sl]]))
        assert s.predictive_variance[g, 6] == v[top[g], 6]
        assert s.mutual_information[g] >= 0.0
    assert s.cluster_size.tolist() == sizes
    assert s.epistemic_total_variance[0] == 0.0  # a single member
    assert np.isnan(s.aleatoric_total_variance[1]) and np.isnan(s.predictive_variance[1, 2])
    assert np.isfinite(s.epistemic_total_variance).all()
    assert np.isfinite(s.aleatoric_total_variance[[0, 2, 3]]).all()


def test_no_groups():
    s = cluster_statistics(np.zeros((0, 3)), np.zeros((0, 7)), np.zeros((0, 7)),
                           np.zeros(0, int), np.zeros(0, int))
    assert len(s.cluster_size) == 0 and s.predictive_variance.shape == (0, 7)


def test_regression_statistics_rejects_unknown_option():
    with pytest.raises(ValueError, match="yaw_variance"):
        regression_statistics(np.zeros((1, 7)), np.zeros((1, 7)), np.array([0]), np.array([1]),
                              np.array([0]), yaw_variance="mean")


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("yaw_deviation", ["wrapped", "raw"])
@pytest.mark.parametrize("yaw_variance", ["top", "mixture"])
def test_compiled_statistics_equal_the_numpy_definitions(seed, yaw_deviation, yaw_variance):
    # cluster_statistics runs one compiled pass (group_statistics); the numpy forms of the
    # same definitions are the reference: groups of 1-5 members, ~100 m coordinates, yaws
    # across +-pi, unknown (NaN) variances on some members, probabilities with zeros
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, 6, size=rng.integers(1, 30))
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    m = int(counts.sum())
    boxes = np.column_stack([rng.normal(100.0, 30.0, (m, 3)), rng.uniform(0.5, 5.0, (m, 3)),
                             rng.uniform(-np.pi, np.pi, m)])
    var = rng.uniform(0.0, 1.0, (m, 7))
    var[rng.random(m) < 0.2] = np.nan
    probs = rng.dirichlet(np.ones(4), m)
    probs[rng.random((m, 4)) < 0.1] = 0.0
    top = starts + rng.integers(0, counts)
    s = cluster_statistics(probs, boxes, var, starts, top, yaw_deviation=yaw_deviation,
                           yaw_variance=yaw_variance)
    se, ae, mi = classification_statistics(probs, starts, counts)
    epi, ale, pred = regression_statistics(boxes, var, starts, counts, top,
                                           yaw_deviation=yaw_deviation,
                                           yaw_variance=yaw_variance)
    np.testing.assert_array_equal(s.cluster_size, counts)
    for got, want in [(s.shannon_entropy, se), (s.aleatoric_entropy, ae),
                      (s.mutual_information, mi), (s.epistemic_variance, epi),
                      (s.aleatoric_variance, ale), (s.predictive_variance, pred),
                      (s.epistemic_total_variance, epi.sum(axis=1)),
                      (s.aleatoric_total_variance, ale.sum(axis=1))]:
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert np.isnan(s.aleatoric_total_variance).any() == np.isnan(ale).any()
