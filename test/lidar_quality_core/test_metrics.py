"""Tests of lidar_quality_core.metrics (cross-checked against scikit-learn)."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from sklearn.calibration import calibration_curve
from sklearn.metrics import (
    accuracy_score,
    average_precision_score,
    r2_score,
    roc_auc_score,
)

from lidar_quality_core.metrics import (
    ReliabilityDiagram,
    accuracy,
    auprc,
    auroc,
    brier,
    ece,
    mae,
    mce,
    r2,
    reliability_diagram,
    summary,
)

# -- strategies ---------------------------------------------------------------------------

binary_with_scores = st.integers(2, 60).flatmap(
    lambda n: st.tuples(
        st.lists(st.integers(0, 1), min_size=n, max_size=n),
        # A few levels only, so ties between and within classes are common.
        st.lists(st.integers(0, 5), min_size=n, max_size=n),
    )
)


# -- cross-checks against scikit-learn -----------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(binary_with_scores)
def test_auroc_auprc_match_sklearn_with_ties(ys):
    y, s = (np.array(v) for v in ys)
    assume(0 < y.sum() < y.size)
    score = s / 5.0
    assert auroc(y, score) == pytest.approx(roc_auc_score(y, score), abs=1e-12)
    assert auprc(y, score) == pytest.approx(average_precision_score(y, score), abs=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_match_sklearn_random_continuous(seed):
    rng = np.random.default_rng(seed)
    n = 500
    y = rng.integers(0, 2, n)
    score = np.clip(0.3 * y + rng.normal(0.35, 0.25, n), 0, 1)
    assert auroc(y, score) == pytest.approx(roc_auc_score(y, score), abs=1e-12)
    assert auprc(y, score) == pytest.approx(average_precision_score(y, score), abs=1e-12)
    assert accuracy(y, score) == pytest.approx(accuracy_score(y, score >= 0.5))
    assert accuracy(y, score, threshold=0.7) == pytest.approx(accuracy_score(y, score >= 0.7))
    yt = rng.normal(size=n)
    yp = yt + rng.normal(scale=0.5, size=n)
    assert r2(yt, yp) == pytest.approx(r2_score(yt, yp), abs=1e-12)
    assert r2(yt, -yp) == pytest.approx(r2_score(yt, -yp), abs=1e-12)  # negative R^2


def test_accuracy_threshold_is_inclusive():
    assert accuracy([1, 0], [0.5, 0.49]) == 1.0
    assert accuracy([1, 0, 1], [1, 0, 0]) == pytest.approx(2 / 3)  # hard labels
    assert accuracy([1, 0], [0.7, 0.6], threshold=0.7) == 1.0


def test_all_same_score():
    y = np.array([0, 1, 1, 0, 1])
    s = np.full(5, 0.42)
    assert auroc(y, s) == pytest.approx(roc_auc_score(y, s)) == pytest.approx(0.5)
    assert auprc(y, s) == pytest.approx(average_precision_score(y, s)) == pytest.approx(0.6)


def test_auroc_extremes_and_negative_scores():
    y = np.array([0, 0, 1, 1])
    assert auroc(y, [-3.0, -2.0, 5.0, 7.0]) == 1.0
    assert auroc(y, [5.0, 7.0, -3.0, -2.0]) == 0.0
    assert auprc(y, [-3.0, -2.0, 5.0, 7.0]) == 1.0


def test_hand_computed_auprc():
    # Descending scores: 0.9(+) 0.8(-) 0.7(+) 0.6(-): AP = 0.5*1 + 0.5*(2/3).
    assert auprc([1, 0, 1, 0], [0.9, 0.8, 0.7, 0.6]) == pytest.approx(0.5 + 1 / 3)


@pytest.mark.parametrize("y", [[1, 1, 1], [0, 0, 0, 0], [True]])
def test_single_class_is_nan_without_warning(y):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(auroc(y, np.linspace(0, 1, len(y))))
        assert math.isnan(auprc(y, np.linspace(0, 1, len(y))))


def test_empty_inputs_are_nan():
    for f in (accuracy, auroc, auprc, r2, mae, brier, ece, mce):
        assert math.isnan(f([], [])), f.__name__


def test_r2_degenerate():
    assert math.isnan(r2([2.0, 2.0, 2.0], [2.0, 2.0, 2.0]))  # constant y_true
    assert math.isnan(r2([2.0, 2.0], [1.0, 3.0]))
    assert math.isnan(r2([1.0], [1.0]))
    assert r2([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 1.0


def test_mae_and_brier():
    assert mae([0.0, 1.0, 0.5], [0.5, 0.5, 0.5]) == pytest.approx(1 / 3)
    assert brier([1, 0], [0.8, 0.4]) == pytest.approx((0.04 + 0.16) / 2)


# -- argument order guard --------------------------------------------------------------------


def test_auroc_argument_order_matters_with_hard_labels():
    # With hard labels, auroc(y, p) is balanced accuracy (TPR + TNR) / 2 = (1/3 + 1) / 2,
    # while the swapped call gives (PPV + NPV) / 2 = (1 + 1/2) / 2.
    y = [1, 1, 1, 0, 0]
    p = [1, 0, 0, 0, 0]
    assert auroc(y, p) == pytest.approx(2 / 3)
    assert auroc(p, y) == pytest.approx(0.75)
    assert auroc(y, p) == pytest.approx(roc_auc_score(y, p))


def test_swapped_continuous_score_rejected():
    y = [0, 1, 1, 0]
    s = [0.1, 0.8, 0.65, 0.3]
    assert auroc(y, s) == 1.0
    for f in (auroc, auprc, accuracy, ece):
        with pytest.raises(ValueError, match="binary"):
            f(s, y)


# -- input validation --------------------------------------------------------------------------


@pytest.mark.parametrize("f", [accuracy, auroc, auprc, r2, mae, brier, ece, mce])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_rejected(f, bad):
    with pytest.raises(ValueError, match="NaN"):
        f([0, 1, 1], [0.2, bad, 0.5])
    with pytest.raises(ValueError, match="NaN"):
        f([0, bad, 1], [0.2, 0.4, 0.5])


@pytest.mark.parametrize("f", [accuracy, auroc, auprc, r2, brier, ece])
def test_length_mismatch_rejected(f):
    with pytest.raises(ValueError, match="length mismatch"):
        f([0, 1, 1], [0.2, 0.5])


def test_probability_range_and_bins_validated():
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        ece([0, 1], [0.5, 1.2])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        reliability_diagram([0, 1], [-0.1, 0.5])
    with pytest.raises(ValueError, match="n_bins"):
        ece([0, 1], [0.5, 0.5], n_bins=0)
    with pytest.raises(ValueError, match="1-D"):
        auroc(np.zeros((2, 2)), np.zeros((2, 2)))


# -- calibration ---------------------------------------------------------------------------------


def test_ece_mce_hand_computed():
    y = [1, 0, 1, 1]
    p = [0.05, 0.15, 0.95, 1.0]
    # bin0: |1 - .05| = .95 (n=1); bin1: |0 - .15| = .15 (n=1); bin9: |1 - .975| (n=2)
    assert ece(y, p) == pytest.approx((0.95 + 0.15 + 2 * 0.025) / 4)
    assert mce(y, p) == pytest.approx(0.95)
    # Two bins: [0, .5) holds .05, .15; [.5, 1] holds .95, 1.0
    assert ece(y, p, n_bins=2) == pytest.approx(0.5 * abs(0.5 - 0.1) + 0.5 * abs(1 - 0.975))


def test_bin_edge_rule():
    rd = reliability_diagram([0, 1, 1, 0, 1], [0.0, 0.3, 0.5, 0.99, 1.0])
    # Left-closed bins: 0.3 -> [0.3, 0.4), 0.5 -> [0.5, 0.6); 1.0 joins 0.99 in the last.
    assert rd.counts.tolist() == [1, 0, 0, 1, 0, 1, 0, 0, 0, 2]
    np.testing.assert_allclose(rd.edges, np.linspace(0, 1, 11))
    assert rd.edges[3] == 0.3 and rd.edges[-1] == 1.0
    assert rd.mean_confidence[9] == pytest.approx(0.995)
    assert rd.accuracy[9] == 0.5


def test_constant_overconfident_predictor():
    y = np.r_[np.ones(600), np.zeros(400)]
    p = np.full(1000, 0.9)
    assert ece(y, p) == pytest.approx(0.3)
    assert mce(y, p) == pytest.approx(0.3)
    rd = reliability_diagram(y, p)
    assert rd.counts[9] == 1000 and rd.counts[:9].sum() == 0


def test_perfectly_calibrated_large_n():
    rng = np.random.default_rng(7)
    n = 200_000
    p = rng.uniform(0, 1, n)
    y = rng.uniform(0, 1, n) < p
    assert ece(y, p) < 0.01
    assert mce(y, p) < 0.03
    # The same data shifted towards over-confidence is clearly miscalibrated.
    assert ece(y, np.clip(p * 1.3, 0, 1)) > 0.05


def test_reliability_consistent_with_ece_and_sklearn():
    rng = np.random.default_rng(3)
    n = 5000
    p = rng.beta(2, 5, n)  # sparse upper bins -> some empty
    y = rng.uniform(size=n) < p ** 0.8
    rd = reliability_diagram(y, p, n_bins=10)
    assert isinstance(rd, ReliabilityDiagram)
    assert rd.counts.sum() == n and rd.edges.shape == (11,)
    ne = rd.nonempty
    assert not ne.all()
    assert np.isnan(rd.mean_confidence[~ne]).all() and np.isnan(rd.accuracy[~ne]).all()
    manual = np.sum(rd.counts[ne] / n * np.abs(rd.accuracy[ne] - rd.mean_confidence[ne]))
    assert ece(y, p) == pytest.approx(manual)
    assert mce(y, p) == pytest.approx(np.nanmax(rd.gaps))
    # sklearn's calibration_curve reports the non-empty bins (no p on an edge here).
    prob_true, prob_pred = calibration_curve(y, p, n_bins=10, strategy="uniform")
    np.testing.assert_allclose(rd.accuracy[ne], prob_true)
    np.testing.assert_allclose(rd.mean_confidence[ne], prob_pred)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.floats(0, 1)), min_size=1, max_size=50),
       st.integers(1, 20))
def test_ece_properties(pairs, n_bins):
    y = np.array([a for a, _ in pairs])
    p = np.array([b for _, b in pairs])
    e, m = ece(y, p, n_bins), mce(y, p, n_bins)
    assert 0.0 <= e <= m + 1e-12 <= 1.0 + 1e-12
    assert reliability_diagram(y, p, n_bins).counts.sum() == y.size


# -- summary -------------------------------------------------------------------------------


def test_summary():
    rng = np.random.default_rng(0)
    y = rng.integers(0, 2, 200)
    conf = np.clip(0.4 * y + rng.uniform(0, 0.6, 200), 0, 1)
    it = rng.uniform(0, 1, 200)
    ip = np.clip(it + rng.normal(0, 0.1, 200), 0, 1)
    s = summary(y, conf, it, ip)
    assert s["auroc"] == auroc(y, conf) and s["auprc"] == auprc(y, conf)
    assert s["ece"] == ece(y, conf) and s["mce"] == mce(y, conf)
    assert s["accuracy"] == accuracy(y, conf) and s["brier"] == brier(y, conf)
    assert s["iou_r2"] == r2(it, ip) and s["iou_mae"] == mae(it, ip)
    assert s["n"] == 200 and s["positive_rate"] == y.mean()
    assert "iou_r2" not in summary(y, conf)
    with pytest.raises(ValueError, match="both"):
        summary(y, conf, it)
