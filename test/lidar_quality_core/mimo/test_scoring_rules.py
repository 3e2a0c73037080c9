"""lidar_quality_core.mimo.scoring_rules against hand-computed values and closed forms."""
import math

import numpy as np
import pytest
from lidar_quality_core.mimo.scoring_rules import (brier_score, classification_nll, energy_score,
                                                   gaussian_nll, marginal_calibration_error, regression_cdf,
                                                   regression_calibration_error, regression_nll,
                                                   sample_energy_score, von_mises_nll)
from scipy.stats import norm


def test_classification_nll_and_brier_by_hand():
    p = np.array([[0.1, 0.7, 0.2], [0.5, 0.25, 0.25], [0.0, 1.0, 0.0]])
    t = np.array([1, 0, 0])
    np.testing.assert_allclose(classification_nll(p, t)[:2], [-math.log(0.7), -math.log(0.5)])
    assert classification_nll(p, t)[2] == pytest.approx(-math.log(1e-12))  # floored, finite
    # (0.1^2 + 0.3^2 + 0.2^2), (0.5^2 + 0.25^2 + 0.25^2), (1 + 1)
    np.testing.assert_allclose(brier_score(p, t), [0.14, 0.375, 2.0])


def test_classification_rules_refuse_bad_targets():
    with pytest.raises(ValueError):
        brier_score(np.full((2, 3), 1 / 3), np.array([0, 3]))
    with pytest.raises(ValueError):
        classification_nll(np.full((2, 3), 1 / 3), np.array([0.5, 1.0]))


def test_gaussian_and_regression_nll_of_a_known_gaussian():
    # N(1, 4) at 3: 0.5 (log(2 pi 4) + 4 / 4)
    assert gaussian_nll([1.0], [4.0], [3.0]) == pytest.approx(0.5 * (math.log(8 * math.pi) + 1))
    mean = np.array([[0, 0, 0, 4, 2, 1.5, 0.3]])
    var = np.array([[0.09, 0.04, 0.01, 0.01, 0.01, 0.01, 0.05]])
    gt = mean + [[0.3, -0.2, 0.1, 0.0, 0.1, 0.0, 0.2]]
    v = var[0, :6] + 1e-2
    d = (gt - mean)[0]
    expect = sum(norm.logpdf(d[i], scale=math.sqrt(v[i])) for i in range(6))
    kappa = 1 / 0.05
    vm = -kappa * math.cos(0.2) + math.log(2 * math.pi * np.i0(kappa))
    assert regression_nll(mean, var, gt)[0] == pytest.approx(-expect + vm, rel=1e-10)


def test_von_mises_nll_limits():
    # kappa -> 0: uniform on the circle
    assert von_mises_nll(0.0, 1e-12, 2.0) == pytest.approx(math.log(2 * math.pi))
    # large kappa at the mean: ~ Gaussian with variance 1/kappa, finite (no I0 overflow)
    k = 1e6
    assert von_mises_nll(0.5, k, 0.5) == pytest.approx(0.5 * math.log(2 * math.pi / k), abs=1e-6)
    # periodic: theta and theta + 2 pi score alike
    assert von_mises_nll(3.1, 50.0, -3.1) == pytest.approx(von_mises_nll(3.1, 50.0, 3.1 + 0.0832),
                                                          abs=1e-3)


def test_energy_score_point_mass_is_the_distance():
    mean = np.array([[1.0, 2.0, 0.0, 4.0, 2.0, 1.5, 0.0]])
    gt = mean + [[3.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0]]
    es = energy_score(mean, np.full((1, 7), 1e-12), gt, jitter=0.0, n_samples=50)
    assert es[0] == pytest.approx(5.0, abs=1e-4)
    # a yaw error across +-pi is small (wrapped)
    gt2 = mean.copy()
    mean2 = mean.copy()
    mean2[0, 6], gt2[0, 6] = math.pi - 0.01, -math.pi + 0.01
    es2 = energy_score(mean2, np.full((1, 7), 1e-12), gt2, jitter=0.0, n_samples=20)
    assert es2[0] == pytest.approx(0.02, abs=1e-4)


def crps_normal(mu, sigma, y):
    z = (y - mu) / sigma
    return sigma * (z * (2 * norm.cdf(z) - 1) + 2 * norm.pdf(z) - 1 / math.sqrt(math.pi))


def test_energy_score_of_a_1d_gaussian_matches_the_crps():
    # in one dimension the energy score is the CRPS, closed form for a normal
    rng = np.random.default_rng(0)
    samples = 1.0 + 2.0 * rng.standard_normal((40000, 3, 1))
    y = np.array([[1.0], [2.5], [-4.0]])
    es = sample_energy_score(samples, y)
    np.testing.assert_allclose(es, [crps_normal(1.0, 2.0, v) for v in y[:, 0]], rtol=0.02)


def test_energy_score_of_box_gaussian_matches_the_crps_per_dimension():
    # only x uncertain (others point masses): the 7-D score is x's CRPS plus the
    # other dimensions' distance (0 here)
    mean = np.zeros((1, 7))
    var = np.full((1, 7), 1e-14)
    var[0, 0] = 0.25
    gt = np.zeros((1, 7))
    gt[0, 0] = 0.4
    es = energy_score(mean, var, gt, jitter=0.0, n_samples=40000)
    assert es[0] == pytest.approx(crps_normal(0.0, 0.5, 0.4), rel=0.03)
    # sharper and right is better than wider and right (proper)
    wide = energy_score(mean, var * 16, gt, jitter=0.0, n_samples=4000)
    assert es[0] < wide[0]


def test_regression_cdf_and_calibration_error():
    rng = np.random.default_rng(1)
    n = 20000
    mean = rng.normal(0, 5, (n, 7))
    mean[:, 6] = rng.uniform(-math.pi, math.pi, n)
    var = rng.uniform(0.01, 0.2, (n, 7))
    gt = mean + rng.standard_normal((n, 7)) * np.sqrt(var)
    cdf = regression_cdf(mean, var, gt)
    assert cdf.shape == (n, 7) and cdf.min() >= 0 and cdf.max() <= 1
    ce = regression_calibration_error(mean, var, gt)
    assert ce["mean"] < 1e-3  # calibrated (yaw: small variance von Mises ~ normal)
    over = regression_calibration_error(mean, var / 9, gt)  # 3x too confident
    assert over["mean"] > 0.02 and np.all(over["per_parameter"] > 0.02)
    # one detection exactly at its mean: F = 0.5 everywhere; levels 1/15 .. 14/15
    one = regression_calibration_error(np.zeros((1, 7)), np.ones((1, 7)), np.zeros((1, 7)))
    lv = np.arange(1, 15) / 15
    expect = np.mean(((lv > 0.5).astype(float) - lv) ** 2)
    np.testing.assert_allclose(one["per_parameter"], expect)


def kumar_reference(probs, labels, n_bins=15):
    """A literal (loop) form of Kumar et al.'s debiased marginal l2 calibration error."""
    out = []
    for k in range(probs.shape[1]):
        p, y = probs[:, k], (labels == k).astype(float)
        s = sorted(p)
        parts = np.array_split(s, min(n_bins, len(s)))
        bounds = sorted(set([(parts[i][-1] + parts[i + 1][0]) / 2 for i in range(len(parts) - 1)]
                            + [1.0]))
        idx = np.searchsorted(bounds, p, side="left")
        tot = 0.0
        for b in range(len(bounds)):
            m = idx == b
            if m.sum() < 2:
                continue
            ybar = y[m].mean()
            var = ybar * (1 - ybar) / (m.sum() - 1)
            tot += m.sum() / len(p) * ((p[m].mean() - ybar) ** 2 - var)
        out.append(max(tot, 0.0))
    return math.sqrt(np.mean(out))


def test_marginal_calibration_error_by_hand_and_against_a_literal_form():
    # all rows (0.9, 0.1) with label 0: every class off by 0.1 -> 0.1
    p = np.tile([0.9, 0.1], (50, 1))
    assert marginal_calibration_error(p, np.zeros(50, int)) == pytest.approx(0.1)
    rng = np.random.default_rng(3)
    logits = rng.normal(0, 2, (3000, 4))
    probs = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    labels = np.array([rng.choice(4, p=r) for r in probs])  # calibrated by construction
    mce = marginal_calibration_error(probs, labels)
    assert mce == pytest.approx(kumar_reference(probs, labels), rel=1e-9)
    assert mce < 0.03
    sharp = probs ** 3 / (probs ** 3).sum(axis=1, keepdims=True)  # overconfident
    assert marginal_calibration_error(sharp, labels) > 3 * mce
    assert math.isnan(marginal_calibration_error(np.zeros((0, 3)), np.zeros(0, int)))
