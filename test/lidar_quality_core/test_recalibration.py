"""Recalibrated meta models: identity coefficients give the base model back, the map is
the documented one, NaN in the signal column counts as its fill value, and a saved pair
loads through the model store like any other and predicts the same."""
import numpy as np
import pytest
from lidar_quality_core.meta_model import MetaModels, fit_estimator, save_pair
from lidar_quality_core.recalibration import (RecalibratedClassifier, RecalibratedRegressor,
                                              logit)

NAMES = ("a", "b", "score")


@pytest.fixture(scope="module")
def base():
    rng = np.random.default_rng(0)
    X = rng.random((300, 3))
    tp = (X[:, 0] + 0.3 * rng.standard_normal(300) > 0.5).astype(float)
    iou = np.clip(X[:, 0] * 0.8 + 0.1 * rng.standard_normal(300), 0, 1)
    return (X, fit_estimator("xgboost", "classification", X, tp),
            fit_estimator("xgboost", "regression", X, iou))


def test_identity_coefficients_are_the_base(base):
    X, clf, reg = base
    c = RecalibratedClassifier(clf, [1.0, 0.0], 0.0, column=2)
    r = RecalibratedRegressor(reg, [1.0, 0.0], 0.0, column=2)
    p = clf.predict_proba(X)[:, 1]
    assert np.allclose(c.predict_proba(X)[:, 1], np.clip(p, 1e-4, 1 - 1e-4), atol=1e-9)
    assert np.allclose(r.predict(X), reg.predict(X), atol=1e-9)
    assert c.n_features_in_ == 3 and list(c.classes_) == [0, 1]


def test_documented_map_and_nan_fill(base):
    X, clf, reg = base
    c = RecalibratedClassifier(clf, [0.5, 2.0], -1.0, column=2, fill=0.25)
    z = 0.5 * logit(clf.predict_proba(X)[:, 1]) + 2.0 * logit(X[:, 2]) - 1.0
    assert np.allclose(c.predict_proba(X)[:, 1], 1 / (1 + np.exp(-z)))
    Xn = X.copy()
    Xn[:5, 2] = np.nan
    zn = 0.5 * logit(clf.predict_proba(Xn[:5])[:, 1]) + 2.0 * 0.25 - 1.0
    assert np.allclose(c.predict_proba(Xn)[:5, 1], 1 / (1 + np.exp(-zn)))
    r = RecalibratedRegressor(reg, [0.5, -1.0], 0.2, column=2, transform="identity")
    assert np.allclose(r.predict(X), 0.5 * reg.predict(X) - X[:, 2] + 0.2)
    with pytest.raises(ValueError, match="transform"):
        RecalibratedRegressor(reg, [1, 0], 0, column=2, transform="log")
    with pytest.raises(ValueError, match="coefficients"):
        RecalibratedRegressor(reg, [1, 0], 0, column=None)


def test_saved_pair_loads_through_the_model_store(base, tmp_path):
    X, clf, reg = base
    c = RecalibratedClassifier(clf, [0.8, 0.4], 0.1, column=2)
    r = RecalibratedRegressor(reg, [0.9, 0.05], 0.02, column=2)
    cp, rp = save_pair(tmp_path, "x", c, r, NAMES, compress=3)
    m = MetaModels(cp, rp, NAMES)
    conf, iou = m.predict(X)
    assert np.allclose(conf, c.predict_proba(X)[:, 1])
    assert np.allclose(iou, np.clip(r.predict(X), 0, 1))
