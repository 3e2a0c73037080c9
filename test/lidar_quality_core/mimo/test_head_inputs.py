"""Tests for lidar_quality_core.mimo.head_inputs (a head's boxes as the merge reads them)."""
import numpy as np
import pytest

from lidar_quality_core.mimo.head_inputs import class_probabilities, ordered_variances


def _numpy_probabilities(fg, valid):
    # the definition (mimo_ros.pipeline's module doc) as numpy steps
    have = ~np.isnan(fg)
    known = have.any(axis=1)
    f = np.where(have, fg, 0.0)
    with np.errstate(invalid="ignore"):
        in_range = ((f >= 0.0) & (f <= 1.0)).all(axis=1)
        bg = np.clip(1.0 - f.sum(axis=1), 0.0, 1.0)
    probs = np.column_stack([bg, f])
    usable = valid & known & in_range
    probs[~usable] = np.nan
    return probs, usable, known, in_range


@pytest.mark.parametrize("seed", range(8))
def test_class_probabilities_equal_their_numpy_definition(seed):
    rng = np.random.default_rng(seed)
    n, c = int(rng.integers(0, 40)), int(rng.integers(1, 6))
    fg = rng.uniform(0.0, 0.4, (n, c))
    fg[rng.random((n, c)) < 0.3] = np.nan            # classes without a hypothesis
    fg[rng.random(n) < 0.1] = np.nan                  # no known class at all
    odd = rng.random((n, c)) < 0.05
    fg[odd] = rng.choice([-0.2, 1.5, np.inf, -np.inf], odd.sum())
    valid = rng.random(n) > 0.1
    probs, usable, known, in_range = class_probabilities(fg, valid)
    want = _numpy_probabilities(fg, valid)
    np.testing.assert_array_equal(probs, want[0])
    for got, w in zip((usable, known, in_range), want[1:]):
        np.testing.assert_array_equal(got, w)


def test_ordered_variances():
    v = np.array([[0.1] * 7, [0.2, -0.1, 0.2, 0.2, 0.2, 0.2, 0.2], [np.inf] + [0.3] * 6,
                  [np.nan] + [0.4] * 6])
    out, bad, in_order = ordered_variances(v, np.arange(4))
    assert in_order and bad == 3
    with np.errstate(invalid="ignore"):
        want = np.where(np.isfinite(v) & (v >= 0.0), v, np.nan)
    np.testing.assert_array_equal(out, want)
    assert not ordered_variances(v, np.array([0, 2, 1, 3]))[2]
    out, bad, in_order = ordered_variances(np.zeros((0, 7)), np.zeros(0, np.int64))
    assert in_order and bad == 0 and out.shape == (0, 7)
