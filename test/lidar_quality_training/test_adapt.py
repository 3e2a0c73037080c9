"""Adaptation on synthetic domains with real XGBoost base models: a shifted detector
score is recalibrated, continued or refitted and the chosen pair beats the shipped one on
new frames of the shifted domain; in the base's own domain the shipped pair is kept; one
frame, one class, the grouping of the folds and the one-standard-error rule."""
import numpy as np
import pytest
from lidar_quality_core.meta_model import fit_estimator
from lidar_quality_training import adapt as A

NAMES = ("size", "points", "score")


def domain(n_frames, seed, *, score_scale=1.0, per_frame=30, sequences=None):
    """Rows of n frames: TP depends on points and the detector's score."""
    rng = np.random.default_rng(seed)
    n = n_frames * per_frame
    quality = rng.random(n)
    points = quality * 100 + 10 * rng.standard_normal(n)
    size = rng.random(n)
    score = np.clip(quality + 0.15 * rng.standard_normal(n), 0.01, 0.99)
    iou = np.clip(quality * 0.9 + 0.05 * rng.standard_normal(n), 0, 1)
    X = np.column_stack([size, points, score * score_scale])
    frame = np.repeat([f"{seed}-{k}" for k in range(n_frames)], per_frame)
    seq = None if sequences is None else np.repeat(
        [f"s{k % sequences}" for k in range(n_frames)], per_frame)
    return A.AdaptData(X, iou >= 0.5, iou, frame, NAMES, "score", "logit", sequence=seq)


@pytest.fixture(scope="module")
def base():
    d = domain(40, 1)
    return (fit_estimator("xgboost", "classification", d.X, d.tp.astype(float)),
            fit_estimator("xgboost", "regression", d.X, d.iou))


def brier(est, d):
    return float(np.mean((A.predict(est, "classification", d.X) - d.tp) ** 2))


def test_a_shifted_score_is_adapted_and_beats_the_shipped_model(base):
    clf, reg = base
    user, test = domain(20, 2, score_scale=0.3), domain(30, 3, score_scale=0.3)
    res = A.adapt(user, clf, reg, n_boot=100)
    assert res.chosen["classification"] != "shipped"
    assert brier(res.classifier, test) < 0.8 * brier(clf, test)
    # every candidate reported with its out-of-fold metrics and 95 % intervals
    assert set(A.STRATEGIES) <= set(res.cv) and "detector score" in res.cv
    for e in res.cv.values():
        lo, hi = e["ci95"]["auroc"]
        assert lo <= e["metrics"]["auroc"] <= hi
    assert res.n_frames == 20 and res.n_rows == 600 and "grouped by frame" in res.scheme
    rec = res.record()
    assert rec["chosen"] == res.chosen and rec["frames"] == 20


def test_in_its_own_domain_the_shipped_model_is_kept(base):
    clf, reg = base
    res = A.adapt(domain(10, 4), clf, reg, n_boot=50)
    assert res.chosen["classification"] in ("shipped", "score", "recalibrate")
    assert brier(res.classifier, domain(30, 5)) <= brier(clf, domain(30, 5)) * 1.1


def test_one_frame_splits_rows_and_says_so(base):
    clf, reg = base
    res = A.adapt(domain(1, 6, score_scale=0.3), clf, reg, n_boot=50)
    assert "one frame" in res.scheme and "optimistic" in res.scheme
    assert res.n_frames == 1
    # one frame cannot show that more trees generalise: only the few-coefficient candidates
    assert set(res.chosen.values()) <= set(A.SIMPLE)
    assert any("tree candidates need" in n for n in res.notes)
    lo, hi = res.cv["shipped"]["ci95"]["auroc"]
    assert hi - lo > 0.01                      # a frame says little: a wide interval


def test_one_class_keeps_the_shipped_classifier(base):
    clf, reg = base
    d = domain(5, 7)
    d = d.rows(np.flatnonzero(d.tp))
    res = A.adapt(d, clf, reg, n_boot=20)
    assert res.chosen["classification"] == "shipped" and res.classifier is clf
    assert any("one class only" in n for n in res.notes)


def test_folds_group_by_sequence_then_block_then_frame(base):
    clf, reg = base
    res = A.adapt(domain(12, 8, sequences=3), clf, reg, n_boot=20)
    assert "grouped by sequence" in res.scheme and "3 sequences" in res.scheme
    d = domain(12, 9)
    d.block = A.frame_blocks(np.repeat("s", 12))[np.repeat(np.arange(12), 30)]
    d.sequence = d.block
    res = A.adapt(d, clf, reg, n_boot=20)
    assert "grouped by sequence" in res.scheme or "blocks" in res.scheme


def test_frame_blocks():
    b = A.frame_blocks(["a"] * 7 + ["b"] * 3, block_frames=5)
    assert b.tolist() == ["a/0"] * 5 + ["a/1"] * 2 + ["b/0"] * 3


def test_one_se_rule_takes_the_simplest_close_candidate():
    units = np.repeat(np.arange(10), 5)
    rng = np.random.default_rng(0)
    noise = rng.random(50) * 0.1
    losses = {"shipped": 0.20 + noise, "recalibrate": 0.199 + noise,
              "fresh": 0.05 + noise}
    assert A.one_se_choice(losses, units, ("shipped", "recalibrate", "fresh")) == "fresh"
    close = {"shipped": 0.200 + noise, "fresh": 0.1995 + noise[::-1]}
    assert A.one_se_choice(close, units, ("shipped", "fresh")) == "shipped"


def test_unknown_candidate_and_empty_data(base):
    clf, reg = base
    with pytest.raises(ValueError, match="unknown candidate"):
        A.adapt(domain(3, 10), clf, reg, strategies=("shipped", "magic"))
    with pytest.raises(ValueError, match="no labelled rows"):
        A.adapt(domain(3, 10).rows(np.zeros(0, int)), clf, reg)


def test_take_in_turn():
    seq = np.array(["a"] * 4 + ["b"] * 2 + ["c"])
    assert A.take_in_turn(seq, 3).tolist() == [0, 4, 6]          # one of each first
    assert A.take_in_turn(seq, 5).tolist() == [0, 1, 4, 5, 6]
    assert A.take_in_turn(seq, None).tolist() == list(range(7))
    assert A.take_in_turn(seq, 99).tolist() == list(range(7))
