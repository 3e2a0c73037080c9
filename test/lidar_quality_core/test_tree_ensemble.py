"""The compiled tree walk against xgboost itself: shipped models, freshly trained ones of
other shapes (shallow, deep, unbalanced trees, missing values, default directions both
ways), rows exactly on split conditions, infinities, and what is left to xgboost."""
from __future__ import annotations

import glob
import math

import numpy as np
import pytest
import xgboost

from lidar_quality_core.model_store import load_model, models_dir, save_model
from lidar_quality_core.tree_ensemble import MAX_FEATURES, MAX_ROWS, pack

SHIPPED = sorted(glob.glob(str(models_dir() / "*" / "*.joblib")))
SHIPPED = [p for p in SHIPPED if "reference" not in p]


def _rows(rng, n, f, nan=0.1):
    X = rng.normal(size=(n, f)) * rng.choice([0.01, 1.0, 100.0], size=(n, f))
    X[rng.random(X.shape) < nan] = np.nan
    return X


def _library(booster, X):
    return booster.inplace_predict(np.asarray(X, np.float64)).astype(np.float32)


def _check(booster, X):
    te, why = pack(booster)
    assert te is not None, why
    got = te.predict(X)
    ref = _library(booster, X)
    assert got.shape == ref.shape
    assert not np.isnan(got).any()
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6 if te.link == "logistic" else 0)
    return te


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.split("/")[-1])
def test_shipped_models_predict_as_xgboost_does(path):
    m = load_model(path)
    assert m.compiled is not None, m.compiled_note
    rng = np.random.default_rng(1)
    X = _rows(rng, 400, m.n_features)
    booster = m.estimator.get_booster()
    _check(booster, X)
    # through LoadedModel: the compiled walk below MAX_ROWS, xgboost above; both agree
    small, large = m.predict(X[:50]), m.predict(np.vstack([X] * 2))
    np.testing.assert_allclose(small, large[:50], rtol=1e-6, atol=1e-6)


def _train(rng, objective, depth, n=600, f=6, missing_frac=0.2, rounds=40, **kw):
    X = _rows(rng, n, f, missing_frac)
    z = np.nan_to_num(X[:, 0], nan=0.3) + 0.5 * np.nan_to_num(X[:, 1] > 0)
    y = (z > 0).astype(int) if objective in ("binary:logistic", "reg:logistic") else z
    booster = xgboost.train({"objective": objective, "max_depth": depth, "eta": 0.3,
                             "min_child_weight": 0, "lambda": 0.1, **kw},
                            xgboost.DMatrix(X, label=y), num_boost_round=rounds)
    return booster, X


@pytest.mark.parametrize("objective", ["binary:logistic", "reg:squarederror",
                                       "reg:logistic"])
@pytest.mark.parametrize("depth", [1, 3, 7])
def test_trained_models_of_other_shapes(objective, depth):
    rng = np.random.default_rng(depth)
    booster, X = _train(rng, objective, depth)
    te = _check(booster, _rows(np.random.default_rng(9), 700, X.shape[1], 0.3))
    assert te.depth <= depth
    # trees of lossguide growth are unbalanced: leaves above the full depth
    lossguide, _ = _train(rng, objective, depth, tree_method="hist", grow_policy="lossguide",
                          max_leaves=5)
    _check(lossguide, _rows(np.random.default_rng(10), 300, X.shape[1], 0.3))


def test_values_on_split_conditions_and_infinities_go_where_xgboost_sends_them():
    rng = np.random.default_rng(3)
    booster, X = _train(rng, "reg:squarederror", 4)
    te, _ = pack(booster)
    # every split condition as a value of its feature, and just below / above it
    rows = []
    for t in range(te.feature.shape[0]):
        for i in range(te.feature.shape[1]):
            thr = te.threshold[t, i]
            if not np.isfinite(thr):
                continue
            for v in (thr, np.nextafter(thr, -np.inf), np.nextafter(thr, np.inf)):
                r = np.zeros(X.shape[1], np.float32)
                r[te.feature[t, i]] = v
                rows.append(r)
    R = np.array(rows[:2000], dtype=np.float64)
    R[::7] = np.inf
    R[1::7] = -np.inf
    R[2::7, 0] = np.nan
    _check(booster, R)


def test_missing_values_follow_the_learned_default_direction_both_ways():
    rng = np.random.default_rng(4)
    booster, X = _train(rng, "reg:squarederror", 3, missing_frac=0.4)
    te, _ = pack(booster)
    assert te.nan_right.any() and (te.nan_right == 0).any()  # both directions are learned
    _check(booster, np.full((5, X.shape[1]), np.nan))


def test_empty_and_single_rows():
    rng = np.random.default_rng(5)
    booster, X = _train(rng, "binary:logistic", 3)
    te, _ = pack(booster)
    assert te.predict(np.zeros((0, X.shape[1]))).shape == (0,)
    _check(booster, X[:1])
    with pytest.raises(ValueError, match=r"\(n, 6\)"):
        te.predict(np.zeros((3, 5)))


def _walk_row_by_row(te, X):
    """The packed trees walked one row and one tree at a time, summed in float32 in tree
    order: what the compiled walk must return bit for bit, however it groups rows."""
    X = np.asarray(X, np.float32)
    inner = (1 << te.depth) - 1
    out = np.empty(len(X), np.float32)
    for r, row in enumerate(X):
        acc = np.float32(te.base_margin)
        for t in range(te.feature.shape[0]):
            i = 0
            for _ in range(te.depth):
                v = row[te.feature[t, i]]
                i = 2 * i + 1 + (1 if v >= te.threshold[t, i] else 0) + (
                    int(te.nan_right[t, i]) if np.isnan(v) else 0)
            acc = np.float32(acc + te.leaf[t, i - inner])
        out[r] = acc
    return out


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 7, 8, 9, 11, 12, 13, 15, 16, 21])
def test_rows_grouped_or_not_give_the_same_bits(n):
    # the walk takes rows eight at a time, then four, then one by one: every remainder
    rng = np.random.default_rng(20 + n)
    booster, X = _train(rng, "binary:logistic", 4, missing_frac=0.3, rounds=25)
    te, _ = pack(booster)
    R = _rows(np.random.default_rng(n), n, X.shape[1], 0.3)
    got, ref = te.margin(R), _walk_row_by_row(te, R)
    assert got.view(np.int32).tolist() == ref.view(np.int32).tolist()
    # a row's margin does not depend on its neighbours
    assert te.margin(R[::-1]).view(np.int32).tolist() == got[::-1].view(np.int32).tolist()


@pytest.mark.parametrize("case", ["multiclass", "poisson", "early_stopping", "categorical",
                                  "too_deep", "missing_zero", "gblinear", "too_many_features"])
def test_what_is_left_to_xgboost_is_said(case):
    rng = np.random.default_rng(6)
    X = _rows(rng, 300, 4, 0.0)
    y = (X[:, 0] > 0).astype(int)
    d = xgboost.DMatrix(X, label=y)
    params, rounds, missing = {"max_depth": 3}, 5, math.nan
    expect = {"multiclass": "multi:softprob", "poisson": "count:poisson",
              "early_stopping": "best iteration", "categorical": "categorical",
              "too_deep": "depth", "missing_zero": "missing value",
              "gblinear": "booster gblinear", "too_many_features": "features >"}[case]
    if case == "multiclass":
        params |= {"objective": "multi:softprob", "num_class": 2}
    elif case == "poisson":
        params |= {"objective": "count:poisson"}
        d = xgboost.DMatrix(X, label=np.abs(X[:, 0]))
    elif case == "early_stopping":
        params |= {"objective": "binary:logistic"}
        b = xgboost.train(params, d, 20, evals=[(d, "train")], early_stopping_rounds=2,
                          verbose_eval=False)
        assert pack(b)[0] is None and expect in pack(b)[1]
        return
    elif case == "categorical":
        import pandas as pd

        c = rng.choice(list("abc"), 300)
        df = pd.DataFrame({"c": pd.Categorical(c), "x": X[:, 0]})
        d = xgboost.DMatrix(df, label=(c == "b").astype(int), enable_categorical=True)
        params |= {"objective": "binary:logistic", "tree_method": "hist"}
    elif case == "too_deep":
        params |= {"objective": "reg:squarederror", "max_depth": 14, "min_child_weight": 0}
        d = xgboost.DMatrix(rng.normal(size=(40000, 4)), label=rng.normal(size=40000))
    elif case == "missing_zero":
        params |= {"objective": "binary:logistic"}
        missing = 0.0
    elif case == "gblinear":
        params = {"objective": "binary:logistic", "booster": "gblinear"}
    elif case == "too_many_features":  # a node's 16-bit code holds the feature index
        wide = rng.normal(size=(30, MAX_FEATURES + 1)).astype(np.float32)
        d = xgboost.DMatrix(wide, label=(wide[:, -1] > 0).astype(int))
        params |= {"objective": "binary:logistic", "max_depth": 1}
        rounds = 1
    b = xgboost.train(params, d, rounds)
    te, why = pack(b, missing)
    assert te is None and expect in why, why


def test_loaded_model_takes_the_walk_for_small_batches_only(tmp_path):
    rng = np.random.default_rng(7)
    X = _rows(rng, MAX_ROWS + 100, 5)
    y = (np.nan_to_num(X[:, 0]) > 0).astype(int)
    clf = xgboost.XGBClassifier(n_estimators=30, max_depth=3, n_jobs=1).fit(X, y)
    save_model(clf, tmp_path / "c.joblib", feature_names=[f"f{i}" for i in range(5)],
               task="classification")
    m = load_model(tmp_path / "c.joblib")
    assert m.compiled is not None and m.compiled_note == ""
    calls = []
    walk = m.compiled.predict
    object.__setattr__(m, "compiled", type("Spy", (), {
        "predict": lambda self, X: calls.append(len(X)) or walk(X)})())
    small = m.predict_confidence(X[:MAX_ROWS])
    large = m.predict_confidence(X)
    assert calls == [MAX_ROWS]  # the large batch went to xgboost
    ref = clf.predict_proba(X)[:, 1]
    np.testing.assert_allclose(small, ref[:MAX_ROWS], atol=1e-6)
    np.testing.assert_array_equal(large, ref.astype(np.float64))
