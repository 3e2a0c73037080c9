"""Tests of lidar_quality_core.model_store."""
from __future__ import annotations

import json
import pickle
import warnings
from datetime import datetime
from pathlib import Path

import joblib
import numpy as np
import pytest
import xgboost as xgb
from sklearn.ensemble import GradientBoostingClassifier, GradientBoostingRegressor
from sklearn.linear_model import LogisticRegression, Ridge

from lidar_quality_core.model_store import (
    MANIFEST_SUFFIX,
    LoadedModel,
    ModelStoreError,
    ModelStoreWarning,
    SettingRule,
    check_training_settings,
    load_model,
    manifest_path_for,
    save_model,
    sha256_file,
)

FEATURES = ["n_points", "range_m", "score", "height_m"]


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(42)
    X = rng.normal(size=(120, len(FEATURES)))
    y_cls = (X[:, 0] + 0.5 * X[:, 2] + rng.normal(scale=0.5, size=120) > 0).astype(int)
    y_reg = 0.3 * X[:, 1] - X[:, 3] + rng.normal(scale=0.1, size=120)
    X_test = rng.normal(size=(30, len(FEATURES)))
    return X, y_cls, y_reg, X_test


@pytest.fixture
def no_unpickle(monkeypatch):
    """Make every unpickling entry point fail loudly."""
    # load_model's compiled tree walk, imported first: numba reads the kernel's cache index
    # with pickle at import (its own file, not a model)
    import lidar_quality_core.tree_ensemble  # noqa: F401 - imported for its cache read

    def boom(*a, **k):
        raise AssertionError("unpickling attempted")

    monkeypatch.setattr(joblib, "load", boom)
    monkeypatch.setattr(joblib.numpy_pickle, "load", boom)
    monkeypatch.setattr(pickle, "load", boom)
    monkeypatch.setattr(pickle, "loads", boom)


def _manifest(path):
    return json.loads(manifest_path_for(path).read_text())


def _rewrite_manifest(path, **changes):
    m = _manifest(path)
    m.update(changes)
    manifest_path_for(path).write_text(json.dumps(m))


@pytest.fixture
def saved_clf(tmp_path, data):
    X, y, _, _ = data
    model = LogisticRegression().fit(X, y)
    path = tmp_path / "lmd_classifier.joblib"
    save_model(model, path, feature_names=FEATURES, task="classification")
    return path, model


# -- round trips ------------------------------------------------------------------------


@pytest.mark.parametrize("make", [
    lambda: GradientBoostingClassifier(n_estimators=20, random_state=0),
    lambda: LogisticRegression(),
])
def test_sklearn_classifier_roundtrip(tmp_path, data, make):
    X, y, _, X_test = data
    model = make().fit(X, y)
    path = tmp_path / "clf.joblib"
    save_model(model, path, feature_names=FEATURES, task="classification",
               training_data={"bag": "synthetic", "n": 120}, metrics={"auroc": np.float64(0.9)})
    lm = load_model(path, expected_features=FEATURES, expected_task="classification")
    assert isinstance(lm, LoadedModel)
    conf = lm.predict_confidence(X_test)
    assert conf.shape == (30,) and conf.dtype == np.float64
    assert np.array_equal(conf, model.predict_proba(X_test)[:, 1])
    assert np.array_equal(lm.predict(X_test), conf)
    assert lm.manifest["metrics"] == {"auroc": 0.9}
    assert lm.manifest["training_data"] == {"bag": "synthetic", "n": 120}


@pytest.mark.parametrize("make", [
    lambda: Ridge(alpha=0.5),
    lambda: GradientBoostingRegressor(n_estimators=20, random_state=0),
])
def test_sklearn_regressor_roundtrip(tmp_path, data, make):
    X, _, y, X_test = data
    model = make().fit(X, y)
    path = tmp_path / "iou_regressor.joblib"
    save_model(model, path, feature_names=FEATURES, task="regression")
    lm = load_model(path, expected_features=FEATURES, expected_task="regression")
    assert np.array_equal(lm.predict_value(X_test), model.predict(X_test))
    assert np.array_equal(lm.predict(X_test), model.predict(X_test))


def test_boolean_labels_positive_class(tmp_path, data):
    X, y, _, X_test = data
    model = LogisticRegression().fit(X, y.astype(bool))
    path = tmp_path / "b.joblib"
    m = save_model(model, path, feature_names=FEATURES, task="classification")
    assert m["positive_class"] is True
    lm = load_model(path)
    assert np.array_equal(lm.predict_confidence(X_test), model.predict_proba(X_test)[:, 1])


def test_manifest_contents(saved_clf):
    path, _ = saved_clf
    mpath = path.with_name("lmd_classifier.joblib.manifest.json")
    assert mpath == manifest_path_for(path) and mpath.is_file()
    m = json.loads(mpath.read_text())
    assert m["model_file"] == "lmd_classifier.joblib"
    assert m["sha256"] == sha256_file(path)
    assert m["format"] == "joblib"
    assert m["task"] == "classification"
    assert m["feature_names"] == FEATURES and m["n_features"] == 4
    assert m["model_id"] == f"lmd_classifier-{m['sha256'][:12]}"
    assert set(m["library_versions"]) == {"python", "numpy", "scikit-learn", "xgboost", "joblib"}
    assert m["library_versions"]["numpy"] == np.__version__
    assert m["library_versions"]["xgboost"] == xgb.__version__
    assert datetime.fromisoformat(m["created"]).tzinfo is not None
    assert m["positive_class"] == 1
    # Only the two files: temp files were renamed away.
    assert sorted(p.name for p in path.parent.iterdir()) == sorted([path.name, mpath.name])


def test_explicit_model_id(tmp_path, data):
    X, y, _, _ = data
    path = tmp_path / "m.joblib"
    save_model(LogisticRegression().fit(X, y), path, feature_names=FEATURES,
               task="classification", model_id="lmd-v3")
    assert load_model(path).model_id == "lmd-v3"


# -- xgboost native --------------------------------------------------------------------


@pytest.mark.parametrize("ext,fmt", [("json", "xgboost-json"), ("ubj", "xgboost-ubj")])
@pytest.mark.parametrize("task", ["classification", "regression"])
def test_xgboost_native_roundtrip_without_pickle(tmp_path, data, request, ext, fmt, task):
    X, y_cls, y_reg, X_test = data
    if task == "classification":
        model = xgb.XGBClassifier(n_estimators=15, max_depth=3).fit(X, y_cls)
        expected = model.predict_proba(X_test)[:, 1]
    else:
        model = xgb.XGBRegressor(n_estimators=15, max_depth=3).fit(X, y_reg)
        expected = model.predict(X_test)
    path = tmp_path / f"model.{ext}"
    m = save_model(model, path, feature_names=FEATURES, task=task)
    assert m["format"] == fmt  # inferred from the extension
    assert m["xgboost"]["objective"] == ("binary:logistic" if task == "classification"
                                         else "reg:squarederror")

    request.getfixturevalue("no_unpickle")
    lm = load_model(path, expected_features=FEATURES, expected_task=task)
    np.testing.assert_allclose(lm.predict(X_test), expected, rtol=0, atol=1e-6)
    assert lm.predict(X_test).shape == (30,)


def test_xgboost_raw_booster_classifier(tmp_path, data, no_unpickle):
    X, y, _, X_test = data
    booster = xgb.train({"objective": "binary:logistic", "max_depth": 2},
                        xgb.DMatrix(X, label=y), num_boost_round=10)
    path = tmp_path / "b.ubj"
    save_model(booster, path, feature_names=FEATURES, task="classification")
    lm = load_model(path)
    np.testing.assert_allclose(lm.predict_confidence(X_test),
                               booster.predict(xgb.DMatrix(X_test)), atol=1e-6)


def test_xgboost_joblib_format_also_works(tmp_path, data):
    X, y, _, X_test = data
    model = xgb.XGBClassifier(n_estimators=5).fit(X, y)
    path = tmp_path / "x.joblib"
    m = save_model(model, path, feature_names=FEATURES, task="classification")
    assert m["format"] == "joblib"
    np.testing.assert_allclose(load_model(path).predict(X_test), model.predict_proba(X_test)[:, 1])


def test_xgboost_save_refusals(tmp_path, data):
    X, y, y_reg, _ = data
    clf = xgb.XGBClassifier(n_estimators=3).fit(X, y)
    with pytest.raises(ModelStoreError, match="needs a '.json' file name"):
        save_model(clf, tmp_path / "m.ubj", feature_names=FEATURES, task="classification",
                   format="xgboost-json")
    with pytest.raises(ModelStoreError, match="XGBClassifier saved with task regression"):
        save_model(clf, tmp_path / "m.json", feature_names=FEATURES, task="regression")
    with pytest.raises(ModelStoreError, match="needs an xgboost model"):
        save_model(LogisticRegression().fit(X, y), tmp_path / "m.json",
                   feature_names=FEATURES, task="classification", format="xgboost-json")
    multi = xgb.XGBClassifier(n_estimators=3).fit(X, (X[:, 0] > 0).astype(int) + (X[:, 1] > 0))
    with pytest.raises(ModelStoreError, match="binary:logistic"):
        save_model(multi, tmp_path / "m.json", feature_names=FEATURES, task="classification")
    reg = xgb.XGBRegressor(n_estimators=3).fit(X, y_reg)
    with pytest.raises(ModelStoreError, match="feature_names has 3"):
        save_model(reg, tmp_path / "m.json", feature_names=FEATURES[:3], task="regression")
    assert list(tmp_path.iterdir()) == []


# -- refusals at load ----------------------------------------------------------------------


def test_tampered_model_hash_mismatch(saved_clf, no_unpickle):
    path, _ = saved_clf
    good = sha256_file(path)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    bad = sha256_file(path)
    with pytest.raises(ModelStoreError) as ei:
        load_model(path)
    msg = str(ei.value)
    assert "SHA-256 mismatch" in msg and path.name in msg
    assert good[:12] in msg and bad[:12] in msg and good not in msg


def test_missing_manifest(saved_clf, no_unpickle):
    path, _ = saved_clf
    manifest_path_for(path).unlink()
    with pytest.raises(ModelStoreError,
                       match=r"missing manifest lmd_classifier\.joblib\.manifest\.json"):
        load_model(path)


def test_missing_model(saved_clf, no_unpickle):
    path, _ = saved_clf
    path.unlink()
    with pytest.raises(ModelStoreError, match="missing model file"):
        load_model(path)


def test_manifest_path_refused_as_model(saved_clf):
    path, _ = saved_clf
    with pytest.raises(ModelStoreError, match="not its manifest"):
        load_model(manifest_path_for(path))


@pytest.mark.parametrize("expected,fragments", [
    (FEATURES + ["intensity"], ["missing from model: ['intensity']"]),
    (FEATURES[:3], ["extra in model: ['height_m']"]),
    (["range_m", "n_points", "score", "height_m"],
     ["reordered", "'range_m' expected at 0, model has it at 1"]),
    (["n_points", "score", "range_m", "width"],
     ["missing from model: ['width']", "extra in model: ['height_m']", "reordered"]),
])
def test_schema_mismatch(saved_clf, no_unpickle, expected, fragments):
    path, _ = saved_clf
    with pytest.raises(ModelStoreError) as ei:
        load_model(path, expected_features=expected)
    msg = str(ei.value)
    assert "feature schema mismatch" in msg and path.name in msg
    for f in fragments:
        assert f in msg


def test_task_mismatch(saved_clf, no_unpickle):
    path, _ = saved_clf
    with pytest.raises(ModelStoreError,
                       match="task mismatch: expected 'regression', model is 'classification'"):
        load_model(path, expected_task="regression")


def test_unknown_format(saved_clf, no_unpickle):
    path, _ = saved_clf
    _rewrite_manifest(path, format="onnx")
    with pytest.raises(ModelStoreError, match="unknown format 'onnx'"):
        load_model(path)


def test_manifest_for_other_file(saved_clf, no_unpickle):
    path, _ = saved_clf
    _rewrite_manifest(path, model_file="other.joblib")
    with pytest.raises(ModelStoreError, match="describes model_file 'other.joblib'"):
        load_model(path)


@pytest.mark.parametrize("content", ["{not json", "[]", json.dumps({"model_file": "x"})])
def test_corrupt_manifest(saved_clf, no_unpickle, content):
    path, _ = saved_clf
    manifest_path_for(path).write_text(content)
    with pytest.raises(ModelStoreError, match="manifest"):
        load_model(path)


def test_version_difference_warns_but_loads(saved_clf, data):
    path, model = saved_clf
    m = _manifest(path)
    m["library_versions"]["scikit-learn"] = "0.1.0"
    _rewrite_manifest(path, library_versions=m["library_versions"])
    with pytest.warns(ModelStoreWarning, match="scikit-learn 0.1.0"):
        lm = load_model(path)
    X_test = data[3]
    assert np.array_equal(lm.predict(X_test), model.predict_proba(X_test)[:, 1])


def test_same_versions_do_not_warn(saved_clf):
    path, _ = saved_clf
    with warnings.catch_warnings():
        warnings.simplefilter("error", ModelStoreWarning)
        load_model(path)


# -- predict-time checks ------------------------------------------------------------------


def test_wrong_column_count(saved_clf):
    path, _ = saved_clf
    lm = load_model(path)
    with pytest.raises(ModelStoreError, match="X has 3 columns, model expects 4"):
        lm.predict(np.zeros((2, 3)))
    with pytest.raises(ModelStoreError, match="2-D"):
        lm.predict(np.zeros(4))


def test_empty_X(tmp_path, saved_clf, data):
    path, _ = saved_clf
    lm = load_model(path)
    for X in (np.zeros((0, 4)), np.zeros(0), []):
        out = lm.predict_confidence(X)
        assert out.shape == (0,) and out.dtype == np.float64
    Xd, _, y, _ = data
    rpath = tmp_path / "r.json"
    save_model(xgb.XGBRegressor(n_estimators=2).fit(Xd, y), rpath, feature_names=FEATURES,
               task="regression")
    assert load_model(rpath).predict_value(np.zeros((0, 4))).shape == (0,)


def test_task_specific_predict(saved_clf):
    path, _ = saved_clf
    lm = load_model(path)
    with pytest.raises(ModelStoreError, match="predict_value on a classification model"):
        lm.predict_value(np.zeros((1, 4)))


# -- save-time checks and atomicity ----------------------------------------------------------


def test_save_validation(tmp_path, data):
    X, y, y_reg, _ = data
    clf = LogisticRegression().fit(X, y)
    with pytest.raises(ModelStoreError, match="fitted on 4 features"):
        save_model(clf, tmp_path / "m.joblib", feature_names=FEATURES[:2], task="classification")
    with pytest.raises(ModelStoreError, match="duplicate"):
        save_model(clf, tmp_path / "m.joblib", feature_names=["a", "a", "b", "c"],
                   task="classification")
    with pytest.raises(ModelStoreError, match="task must be"):
        save_model(clf, tmp_path / "m.joblib", feature_names=FEATURES, task="ranking")
    with pytest.raises(ModelStoreError, match="no predict_proba"):
        save_model(Ridge().fit(X, y_reg), tmp_path / "m.joblib", feature_names=FEATURES,
                   task="classification")
    three = LogisticRegression().fit(X, np.digitize(X[:, 0], [-0.5, 0.5]))
    with pytest.raises(ModelStoreError, match="only binary"):
        save_model(three, tmp_path / "m.joblib", feature_names=FEATURES, task="classification")
    with pytest.raises(ModelStoreError, match="unknown format"):
        save_model(clf, tmp_path / "m.joblib", feature_names=FEATURES, task="classification",
                   format="pickle")
    assert list(tmp_path.iterdir()) == []


class _Unpicklable:
    classes_ = np.array([0, 1])
    n_features_in_ = 4

    def predict_proba(self, X):  # pragma: no cover - never called
        return np.zeros((len(X), 2))

    def __reduce__(self):
        raise RuntimeError("cannot pickle")


def test_failed_save_keeps_previous_pair(saved_clf, data):
    path, model = saved_clf
    before = (path.read_bytes(), manifest_path_for(path).read_text())
    with pytest.raises(RuntimeError, match="cannot pickle"):
        save_model(_Unpicklable(), path, feature_names=FEATURES, task="classification")
    assert (path.read_bytes(), manifest_path_for(path).read_text()) == before
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name, path.name + MANIFEST_SUFFIX]
    X_test = data[3]
    assert np.array_equal(load_model(path).predict(X_test), model.predict_proba(X_test)[:, 1])


def test_overwrite_updates_pair(saved_clf, data):
    path, _ = saved_clf
    X, y, _, X_test = data
    new = GradientBoostingClassifier(n_estimators=5, random_state=1).fit(X, y)
    save_model(new, path, feature_names=FEATURES, task="classification")
    assert np.array_equal(load_model(path).predict(X_test), new.predict_proba(X_test)[:, 1])


def test_model_file_is_world_readable(saved_clf):
    path, _ = saved_clf
    assert path.stat().st_mode & 0o044 == 0o044
    assert Path(manifest_path_for(path)).stat().st_mode & 0o044 == 0o044


# -- multiclass and multi-output ------------------------------------------------------


@pytest.fixture(scope="module")
def data3(data):
    X, _, _, X_test = data
    y3 = np.digitize(X[:, 0] + 0.3 * X[:, 1], [-0.5, 0.5])  # 3 classes
    return X, y3, X_test


@pytest.mark.parametrize("kind", ["sklearn", "xgb-joblib", "xgb-json", "xgb-ubj", "booster"])
def test_multiclass_roundtrip(tmp_path, data3, kind, monkeypatch):
    X, y3, X_test = data3
    names = ["bg", "car", "ped"]
    if kind == "sklearn":
        model, path = LogisticRegression(max_iter=500).fit(X, y3), tmp_path / "m.joblib"
        expected = model.predict_proba(X_test)
    elif kind == "booster":
        model = xgb.train({"objective": "multi:softprob", "num_class": 3, "max_depth": 2},
                          xgb.DMatrix(X, label=y3), num_boost_round=5)
        path, expected = tmp_path / "m.ubj", model.predict(xgb.DMatrix(X_test))
    else:
        model = xgb.XGBClassifier(n_estimators=8, max_depth=2).fit(X, y3)
        path = tmp_path / ("m.joblib" if kind == "xgb-joblib" else f"m.{kind[4:]}")
        expected = model.predict_proba(X_test)
    m = save_model(model, path, feature_names=FEATURES, task="multiclass", class_names=names)
    assert m["classes"] == [0, 1, 2] and m["class_names"] == names
    lm = load_model(path, expected_task="multiclass")
    p = lm.predict(X_test)
    assert p.shape == (30, 3) and lm.class_names == tuple(names) and lm.classes == (0, 1, 2)
    np.testing.assert_allclose(p, expected, atol=1e-6)
    np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-5)
    assert lm.predict_proba(np.empty((0, 4))).shape == (0, 3)
    with pytest.raises(ModelStoreError, match="predict_confidence on a multiclass"):
        lm.predict_confidence(X_test)


def test_multiclass_refusals(tmp_path, data3, data):
    X, y3, _ = data3
    _, y2, y_reg, _ = data
    with pytest.raises(ModelStoreError, match="multi:softprob"):
        save_model(xgb.XGBClassifier(n_estimators=2).fit(X, y2), tmp_path / "a.json",
                   feature_names=FEATURES, task="multiclass")
    with pytest.raises(ModelStoreError, match="binary"):
        save_model(LogisticRegression().fit(X, y3), tmp_path / "b.joblib",
                   feature_names=FEATURES, task="classification")
    with pytest.raises(ModelStoreError, match="class_names"):
        save_model(LogisticRegression().fit(X, y3), tmp_path / "c.joblib",
                   feature_names=FEATURES, task="multiclass", class_names=["a", "b"])
    path = tmp_path / "d.joblib"
    save_model(LogisticRegression(max_iter=500).fit(X, y3), path, feature_names=FEATURES,
               task="multiclass")
    m = _manifest(path)
    m["classes"] = [0, 1, 3]
    manifest_path_for(path).write_text(json.dumps(m))
    with pytest.raises(ModelStoreError, match="differ from the manifest"):
        load_model(path)
    path = tmp_path / "e.json"
    save_model(xgb.XGBClassifier(n_estimators=2).fit(X, y3), path, feature_names=FEATURES,
               task="multiclass")
    _rewrite_manifest(path, classes=[0, 1])
    with pytest.raises(ModelStoreError, match="3 classes"):
        load_model(path)


def test_multi_output_regression(tmp_path, data):
    X, _, y_reg, X_test = data
    Y = np.stack([y_reg, 2 * y_reg + X[:, 0]], axis=1)
    model = Ridge().fit(X, Y)
    path = tmp_path / "r.joblib"
    save_model(model, path, feature_names=FEATURES, task="regression", target_names=["a", "b"])
    lm = load_model(path)
    assert lm.target_names == ("a", "b")
    np.testing.assert_allclose(lm.predict(X_test), model.predict(X_test))
    assert lm.predict_value(np.empty((0, 4))).shape == (0, 2)
    with pytest.raises(ModelStoreError, match="target_names need a regression"):
        save_model(LogisticRegression().fit(X, data[1]), tmp_path / "x.joblib",
                   feature_names=FEATURES, task="classification", target_names=["a"])


def test_models_dir(monkeypatch, tmp_path):
    from lidar_quality_core.model_store import models_dir

    monkeypatch.delenv("LQ_MODELS_DIR", raising=False)
    assert (models_dir().parent / "lidar_quality_core").is_dir()
    monkeypatch.setenv("LQ_MODELS_DIR", str(tmp_path))
    assert models_dir() == tmp_path


# -- the shipped models under tampering (issue 8 hardening) --------------------------------

SHIPPED = sorted(Path(__file__).resolve().parents[2].joinpath("models").glob("*/*.joblib"))


def _copy_pair(path: Path, tmp_path: Path) -> Path:
    dst = tmp_path / path.name
    dst.write_bytes(path.read_bytes())
    manifest_path_for(dst).write_bytes(manifest_path_for(path).read_bytes())
    return dst


def test_models_are_shipped():
    assert {p.parent.name for p in SHIPPED} >= {"lmd", "lms", "mimo"}


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shipped_model_one_byte_changed_is_refused(path, tmp_path, no_unpickle):
    dst = _copy_pair(path, tmp_path)
    raw = bytearray(dst.read_bytes())
    raw[len(raw) // 3] = (raw[len(raw) // 3] + 1) % 256
    dst.write_bytes(bytes(raw))
    with pytest.raises(ModelStoreError, match=rf"{dst.name}.*SHA-256 mismatch"):
        load_model(dst, expected_features=_manifest(path)["feature_names"])


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shipped_model_with_a_manifest_naming_other_features_is_refused(path, tmp_path,
                                                                        no_unpickle):
    dst = _copy_pair(path, tmp_path)
    names = _manifest(path)["feature_names"]
    _rewrite_manifest(dst, feature_names=["range_m"] + names[1:])
    with pytest.raises(ModelStoreError, match=rf"{dst.name}.*feature schema mismatch.*range_m"):
        load_model(dst, expected_features=names)


def test_shipped_lms_model_for_another_class_count_is_refused(request):
    from lms_ros.pipeline import LmsSettings, default_model_paths

    request.getfixturevalue("no_unpickle")  # after the import: numba's caches use pickle
    settings = LmsSettings()
    fewer = LmsSettings(class_names=settings.class_names[:-1]).metric_names()
    for path in default_model_paths():
        with pytest.raises(ModelStoreError) as ei:
            load_model(path, expected_features=fewer)
        msg = str(ei.value)
        assert path.name in msg and "feature schema mismatch" in msg
        assert "extra in model" in msg and settings.class_names[-1] in msg


# -- training settings --------------------------------------------------------------------
RULES = (SettingRule("mode", fix="set mode to {model}"),
         SettingRule("classes"),
         SettingRule("merge.eps", exact=False, fix="set eps to {model}"),
         SettingRule("threshold", exact=False, when=("mode", ("a",))))
RECORDED = {"mode": "a", "classes": ["car", "truck"], "merge": {"eps": 0.5},
            "threshold": 0.3}


def _with_settings(settings, section="settings"):
    return {"model_file": "m.joblib", "training_data": {section: settings}}


def test_training_settings_equal_give_no_finding():
    current = {"mode": "a", "classes": ("car", "truck"), "merge": {"eps": 0.5 + 1e-15},
               "threshold": 0.3, "unrelated": 1}
    assert check_training_settings(_with_settings(RECORDED), current, RULES) == []


def test_training_settings_exact_mismatch_refused_with_both_values_and_fix():
    current = {**RECORDED, "mode": "b", "classes": ["truck", "car"]}
    with pytest.raises(ModelStoreError) as e:
        check_training_settings(_with_settings(RECORDED), current, RULES)
    text = str(e.value)
    assert text.startswith("m.joblib: trained with other settings than the node's: ")
    assert "mode: model trained with 'a', node set to 'b' (fix: set mode to 'a')" in text
    assert 'classes: model trained with ["car", "truck"], node set to ["truck", "car"]' in text


def test_training_settings_other_values_warn():
    current = {**RECORDED, "merge": {"eps": 0.7}, "threshold": 0.4}
    found = check_training_settings(_with_settings(RECORDED), current, RULES)
    assert len(found) == 2
    assert found[0].startswith("m.joblib: eps: model trained with 0.5, node set to 0.7")
    assert "(set eps to 0.5)" in found[0]
    assert "threshold: model trained with 0.3, node set to 0.4" in found[1]
    # the threshold rule applies only in mode "a"
    rules = RULES[2:]
    assert check_training_settings(_with_settings(RECORDED), {**current, "mode": "b"},
                                   rules) == [found[0]]


def test_training_settings_not_recorded_warn_that_they_cannot_be_checked():
    found = check_training_settings({"model_file": "m.joblib", "training_data": {}},
                                    RECORDED, RULES)
    assert len(found) == 1
    assert "cannot check mode, classes, merge.eps, threshold" in found[0]
    assert "records no training settings" in found[0]
    partial = check_training_settings(_with_settings({"mode": "a"}), RECORDED, RULES)
    assert len(partial) == 1 and "cannot check classes, merge.eps, threshold" in partial[0]


def test_training_settings_section_and_model_value():
    manifest = {**_with_settings({"eps": 0.5}, "merge_settings"), "feature_names": ["a", "p"]}
    rules = (SettingRule("eps"), SettingRule("uses_p", model_value=lambda m: "p" in
                                             m["feature_names"]))
    assert check_training_settings(manifest, {"eps": 0.5, "uses_p": True}, rules,
                                   section="merge_settings") == []
    with pytest.raises(ModelStoreError, match="uses_p: model trained with true, node set "
                                              "to false"):
        check_training_settings(manifest, {"eps": 0.5, "uses_p": False}, rules,
                                section="merge_settings")
