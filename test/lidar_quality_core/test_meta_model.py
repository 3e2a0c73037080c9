"""Meta model helpers: grouped folds, cross validation, greedy selection, the model pair."""
import numpy as np
import pytest
from lidar_quality_core import meta_model as mm
from lidar_quality_core.model_store import ModelStoreError


def _data(n=600, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 5))
    iou = 1 / (1 + np.exp(-(1.5 * X[:, 0] - X[:, 2])))  # depends on features 0 and 2 only
    y = (iou + 0.1 * rng.normal(size=n) > 0.5).astype(int)
    groups = np.repeat(np.arange(12), n // 12)
    return X, y, iou, groups


def test_group_folds_partition_groups():
    groups = np.repeat(np.arange(7), 5)
    folds = mm.group_folds(groups, 3, seed=1)
    assert len(folds) == 3
    seen = np.concatenate([va for _, va in folds])
    assert np.array_equal(np.sort(seen), np.arange(groups.size))
    for tr, va in folds:
        assert not set(groups[tr]) & set(groups[va])
    assert len(mm.group_folds(groups[:10], 10)) == 2  # fewer groups than folds
    with pytest.raises(ValueError):
        mm.group_folds(np.zeros(5), 3)


@pytest.mark.parametrize("kind", mm.KINDS)
def test_every_kind_learns_both_tasks(kind):
    X, y, iou, groups = _data()
    X[::17, 1] = np.nan  # missing values must be accepted by every kind
    cv = mm.cross_validate(X, y, groups, task="classification", kind=kind, n_folds=3)
    assert cv.mean_std()["val"]["auroc"][0] > 0.8
    assert np.isfinite(cv.oof).all()
    cvr = mm.cross_validate(X, iou, groups, task="regression", kind=kind, n_folds=3)
    assert cvr.mean_std()["val"]["r2"][0] > 0.5


def test_classification_needs_binary_targets():
    X, y, iou, groups = _data()
    with pytest.raises(ValueError, match="0/1"):
        mm.fit_estimator("linear", "classification", X, iou)
    with pytest.raises(ValueError, match="kind"):
        mm.make_estimator("svm", "classification")


def test_greedy_selection_finds_the_informative_features():
    X, y, iou, groups = _data(900)
    g = mm.greedy_selection(X, iou, [f"f{i}" for i in range(5)], groups, task="regression",
                            kind="linear", max_features=4)
    assert g.selected[:2] == ["f0", "f2"]
    assert g.metric == "r2" and np.all(np.diff(g.scores) >= 5e-4)
    assert len(g.selected) <= 3  # the noise features add less than the gain threshold


def test_meta_models_pair(tmp_path):
    X, y, iou, groups = _data()
    names = [f"f{i}" for i in range(5)]
    clf = mm.fit_estimator("xgboost", "classification", X, y)
    reg = mm.fit_estimator("xgboost", "regression", X, iou)
    cpath, rpath = mm.save_pair(tmp_path, "toy", clf, reg, names)
    pair = mm.MetaModels(cpath, rpath, names)
    Xq = X[:4].copy()
    Xq[1] = np.nan  # an invalid row: no score at all
    Xq[2, 3] = np.inf  # a single bad value is treated as missing
    conf, pred = pair.predict(Xq)
    assert np.isnan(conf[1]) and np.isnan(pred[1])
    ok = [0, 2, 3]
    assert np.all((conf[ok] >= 0) & (conf[ok] <= 1)) and np.all((pred[ok] >= 0) & (pred[ok] <= 1))
    np.testing.assert_allclose(conf[0], clf.predict_proba(X[:1])[0, 1], rtol=1e-6)
    assert pair.confidence_model_id.startswith("toy_classifier-")
    with pytest.raises(ModelStoreError, match="schema"):
        mm.MetaModels(cpath, rpath, names[::-1])
    with pytest.raises(ModelStoreError, match="task"):
        mm.MetaModels(rpath, cpath, names)



def test_meta_models_pair_walk_equals_each_model_alone(tmp_path):
    # both compiled walks in one pass (tree_ensemble.predict_pair) against each model's
    # own predict on the rows the definition keeps (+-inf as missing, all-NaN rows out):
    # the same bits; beyond the walk's batch size xgboost's predict gives the same values
    from lidar_quality_core.tree_ensemble import MAX_ROWS

    X, y, iou, _ = _data(300, seed=3)
    names = [f"f{i}" for i in range(5)]
    cpath, rpath = mm.save_pair(tmp_path, "toy", mm.fit_estimator("xgboost", "classification", X, y),
                                mm.fit_estimator("xgboost", "regression", X, iou), names)
    pair = mm.MetaModels(cpath, rpath, names)
    assert pair._pair is not None
    rng = np.random.default_rng(4)
    Xq = rng.normal(size=(MAX_ROWS + 40, 5)) * 2
    Xq[rng.random(Xq.shape) < 0.2] = np.nan
    Xq[rng.random(Xq.shape) < 0.05] = np.inf
    Xq[rng.random(Xq.shape) < 0.05] = -np.inf
    Xq[3] = np.nan
    Xq[7] = [np.nan, np.inf, np.nan, -np.inf, np.nan]  # infinities only: missing, still a row
    Xq[9, 1] = 1e39  # beyond float32: inf after the conversion, as numpy converts it
    ok = ~np.isnan(Xq).all(axis=1)
    clean = np.where(np.isinf(Xq), np.nan, Xq)
    for n in (1, 5, 8, 13, 55, MAX_ROWS):
        conf, pred = pair.predict(Xq[:n])
        ref_c = np.full(n, np.nan)
        ref_p = np.full(n, np.nan)
        with np.errstate(over="ignore"):  # numpy says so when it casts 1e39 to float32
            ref_c[ok[:n]] = np.clip(pair.classifier.predict_confidence(clean[:n][ok[:n]]), 0, 1)
            ref_p[ok[:n]] = np.clip(pair.regressor.predict_value(clean[:n][ok[:n]]), 0, 1)
        assert conf.tobytes() == ref_c.tobytes() and pred.tobytes() == ref_p.tobytes(), n
    big_c, big_p = pair.predict(Xq)  # more rows than the walk takes: each model's library
    small_c, small_p = pair.predict(Xq[:MAX_ROWS])
    np.testing.assert_allclose(big_c[:MAX_ROWS], small_c, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(big_p[:MAX_ROWS], small_p, rtol=1e-6, atol=1e-6)
    assert np.isnan(big_c[3]) and np.isnan(small_p[3]) and not np.isnan(small_c[7])
    assert pair.predict(np.zeros((0, 5)))[0].shape == (0,)


LMD = {"proposal_mode": "threshold", "iou_threshold": 0.5, "proposal_score_threshold": 0.0,
       "nms_iou_threshold": 0.1, "nms_score_threshold": 0.1,
       "class_names": ["car", "truck", "pedestrian", "cyclist"], "class_score_features": False}


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """A real xgboost pair saved with LMD settings recorded, and one without (older)."""
    X, y, iou, _ = _data(200)
    names = [f"f{i}" for i in range(5)]
    clf = mm.fit_estimator("xgboost", "classification", X, y)
    reg = mm.fit_estimator("xgboost", "regression", X, iou)
    root = tmp_path_factory.mktemp("setting_pairs")
    return names, {
        "recorded": mm.save_pair(root / "recorded", "lmd_threshold", clf, reg, names,
                                 training_data=mm.settings_record(LMD, "lmd")),
        "older": mm.save_pair(root / "older", "lmd_threshold", clf, reg, names)}


def test_meta_models_refuse_other_training_settings(pairs):
    names, p = pairs
    for change, expect in (({"proposal_mode": "exact"},
                            "proposal_mode: model trained with 'threshold', node set to "
                            "'exact'"),
                           ({"class_names": ["truck", "car", "pedestrian", "cyclist"]},
                            'class_names: model trained with ["car", "truck", "pedestrian", '
                            '"cyclist"], node set to ["truck", "car", "pedestrian", '
                            '"cyclist"]')):
        with pytest.raises(ModelStoreError) as e:
            mm.MetaModels(*p["recorded"], names, settings={**LMD, **change}, method="lmd")
        assert expect in str(e.value) and "fix: set" in str(e.value)
    # without settings only the schema is checked (the nodes always pass them)
    mm.MetaModels(*p["recorded"], names)


def test_meta_models_warn_once_per_pair(pairs):
    names, p = pairs
    got = []
    pair = mm.MetaModels(*p["recorded"], names, method="lmd", warn=got.append,
                         settings={**LMD, "iou_threshold": 0.6, "nms_iou_threshold": 0.3})
    assert got == pair.warnings and len(got) == 1
    assert got[0].startswith("lmd_threshold_classifier.joblib, "
                             "lmd_threshold_regressor.joblib: iou_threshold: model trained "
                             "with 0.5, node set to 0.6")
    assert mm.MetaModels(*p["recorded"], names, settings=LMD, method="lmd").warnings == []


def test_meta_models_without_recorded_settings_load_with_a_warning(pairs):
    names, p = pairs
    with pytest.warns(mm.ModelStoreWarning, match="cannot check proposal_mode.*records no "
                                                  "training settings"):
        pair = mm.MetaModels(*p["older"], names, settings=LMD, method="lmd")
    assert pair.predict(np.zeros((1, 5)))[0].shape == (1,)


def test_mimo_use_points_comes_from_the_feature_schema(tmp_path):
    # mimo-train recorded the dataset's use_points (true) for both pairs: the schema decides
    from lidar_quality_core.model_store import read_manifest

    X, y, iou, _ = _data(200)
    names = ["cluster_size", "score", "class", "distance", "head_fraction"]
    clf = mm.fit_estimator("linear", "classification", X, y)
    reg = mm.fit_estimator("linear", "regression", X, iou)
    merge = {"score_type": "probabilities", "background_index": 0, "yaw_deviation": "wrapped"}
    rec = {"merge_settings": {"use_points": True, "class_names": ["car"], "merge": merge}}
    c, r = mm.save_pair(tmp_path, "mimo", clf, reg, names, training_data=rec)
    current = {"use_points": False, "class_names": ["car"], "merge": merge}
    assert mm.check_settings(read_manifest(c), current, "mimo") == [
        "mimo_classifier.joblib: cannot check num_heads, merge.eps, merge.voting, "
        "merge.min_cluster_size, merge.class_aware, merge.temperature, merge.yaw_variance "
        "against the settings in use: the manifest does not record them; a mismatch would "
        "go unnoticed (retrain to record them)"]
    with pytest.raises(ModelStoreError, match="use_points: model trained with false, node "
                                              "set to true"):
        mm.check_settings(read_manifest(c), {**current, "use_points": True}, "mimo")
    with pytest.raises(ValueError, match="method"):
        mm.check_settings(read_manifest(c), current, "lmx")


def test_models_without_a_recorded_profile_have_none(tmp_path):
    """Models saved before profiles were recorded (the shipped ones until retrained)."""
    rng = np.random.default_rng(0)
    X, names = rng.normal(size=(200, 3)), ["a", "b", "c"]
    y = (X[:, 0] > 0).astype(float)
    clf = mm.fit_estimator("linear", "classification", X, y)
    reg = mm.fit_estimator("linear", "regression", X, X[:, 1])
    old = mm.MetaModels(*mm.save_pair(tmp_path / "old", "toy", clf, reg, names), names)
    assert old.domain_profile is None
    prof = mm.training_profile(X, names, {"score": y})
    new = mm.MetaModels(*mm.save_pair(tmp_path / "new", "toy", clf, reg, names,
                                   domain_profile=prof), names)
    assert set(new.domain_profile.quantities) == {"a", "b", "c", "score"}
    assert new.domain_profile.quantities["a"].count == 200
