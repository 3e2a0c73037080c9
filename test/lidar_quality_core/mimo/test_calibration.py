"""lidar_quality_core.mimo.calibration: F1-optimal thresholds and temperature scaling."""
import numpy as np
import pytest
from lidar_quality_core.mimo.calibration import (Recalibration, apply_temperature, f1_optimal_threshold,
                                                 fit_temperature)


def test_f1_threshold_on_a_toy_set():
    # scores descending with TP flags; 4 GT boxes
    scores = [0.9, 0.8, 0.7, 0.6, 0.5, 0.4]
    tp = [1, 1, 0, 1, 0, 0]
    # F1 at >= 0.9: 2/(1+4)=0.4; 0.8: 4/6=0.667; 0.7: 4/7; 0.6: 6/8=0.75; 0.5: 6/9; 0.4: 0.6
    thr, f1 = f1_optimal_threshold(scores, tp, 4)
    assert thr == 0.6 and f1 == pytest.approx(0.75)
    thr, f1 = f1_optimal_threshold([0.8, 0.6, 0.5], [1, 0, 1], 2)
    # >=0.8: 2/3; >=0.6: 2/4; >=0.5: 4/5 -> 0.5
    assert thr == 0.5 and f1 == pytest.approx(0.8)
    thr, f1 = f1_optimal_threshold([0.8, 0.6], [1, 1], 4)  # 2/5, 4/6 -> 0.6
    assert thr == 0.6
    thr, f1 = f1_optimal_threshold([0.9, 0.3], [1, 0], 1)
    assert thr == 0.9 and f1 == 1.0
    # tied F1: (>= 0.7: TP 1 of 1 det, 3 GT -> 0.5) vs (>= 0.2: 2 TP, 5 det -> 0.5): higher wins
    thr, f1 = f1_optimal_threshold([0.7, 0.6, 0.5, 0.3, 0.2], [1, 0, 0, 0, 1], 3)
    assert thr == 0.7 and f1 == pytest.approx(0.5)
    assert f1_optimal_threshold([], [], 3) == (0.0, pytest.approx(float("nan"), nan_ok=True))


def test_temperature_fit_recovers_a_known_temperature():
    rng = np.random.default_rng(0)
    n, k, t_true = 20000, 5, 2.5
    z = rng.normal(0, 3, (n, k))
    true_p = np.exp(z / t_true) / np.exp(z / t_true).sum(axis=1, keepdims=True)
    target = (rng.random(n)[:, None] > np.cumsum(true_p, axis=1)).sum(axis=1)
    shown = np.exp(z) / np.exp(z).sum(axis=1, keepdims=True)  # overconfident by t_true
    t = fit_temperature(shown, target)
    assert t == pytest.approx(t_true, rel=0.05)
    np.testing.assert_allclose(apply_temperature(shown, t_true), true_p, atol=1e-9)
    # the fitted temperature lowers the NLL
    def nll(p):
        return -np.mean(np.log(p[np.arange(n), target]))
    assert nll(apply_temperature(shown, t)) < nll(shown)
    # too little data or one target class: identity
    assert fit_temperature(shown[:5], target[:5]) == 1.0
    assert fit_temperature(shown, np.zeros(n, int)) == 1.0


def test_apply_temperature_keeps_the_argmax_and_takes_per_row_values():
    p = np.array([[0.1, 0.6, 0.3], [0.2, 0.2, 0.6]])
    q = apply_temperature(p, np.array([1.0, 3.0]))
    np.testing.assert_allclose(q[0], p[0])
    assert np.argmax(q[1]) == 2 and q[1, 2] < 0.6
    np.testing.assert_allclose(q.sum(axis=1), 1.0)


def test_recalibration_per_class():
    rng = np.random.default_rng(1)
    n = 4000
    names = ("car", "pedestrian", "cyclist")
    col = np.where(rng.random(n) < 0.5, 1, 2)            # car / pedestrian columns
    scores = rng.random(n)
    # cars: TP iff score > 0.3; pedestrians: TP iff score > 0.7
    tp = np.where(col == 1, scores > 0.3, scores > 0.7)
    n_gt = {"car": int(tp[col == 1].sum()), "pedestrian": int(tp[col == 2].sum())}
    # distributions [bg, car, ped, cyc] with the score on the label, background the rest
    probs = np.zeros((n, 4))
    probs[np.arange(n), col] = scores
    probs[:, 0] = 1 - scores
    target = np.where(tp, col, 0)
    r = Recalibration.fit(names, col, tp, n_gt, probs, target)
    assert r.raw_thresholds["car"] == pytest.approx(0.3, abs=0.01)
    assert r.raw_thresholds["pedestrian"] == pytest.approx(0.7, abs=0.01)
    assert r.thresholds["cyclist"] == 0.0 and r.temperatures["cyclist"] == 1.0
    assert r.f1["car"] == pytest.approx(1.0)
    # above the thresholds every target is the label: one target class, T = 1 by rule, and
    # the thresholds are the lowest TP scores
    assert r.temperatures == {"car": 1.0, "pedestrian": 1.0, "cyclist": 1.0}
    keep, cal = r.apply(col, probs)
    assert np.array_equal(keep, tp)
    np.testing.assert_allclose(cal, probs[keep])
    # pedestrians: a quarter of the kept ones are background; the scores (> 0.7) are too
    # low for the TPs and too high for the others -> fitted T != 1, NLL lower
    bg = (col == 2) & tp & (rng.random(n) < 0.25)
    target2 = np.where(bg, 0, target)
    r2 = Recalibration.fit(names, col, tp & ~bg, n_gt, probs, target2)
    ped = (col == 2) & (scores >= r2.raw_thresholds["pedestrian"])
    assert r2.temperatures["pedestrian"] != 1.0
    cal2 = r2.calibrate(col, probs)
    np.testing.assert_allclose(cal2.sum(axis=1), 1.0)
    def nll(p):
        return -np.mean(np.log(p[ped][np.arange(ped.sum()), target2[ped]]))
    assert nll(cal2) < nll(probs)
    # the final thresholds are on the scaled scores: F1-optimal there
    sc = cal2[np.arange(n), col]
    sel = col == 2
    assert r2.thresholds["pedestrian"] == f1_optimal_threshold(sc[sel], (tp & ~bg)[sel],
                                                               n_gt["pedestrian"])[0]
    assert np.array_equal(r2.keep(col, cal2)[sel], sc[sel] >= r2.thresholds["pedestrian"])
