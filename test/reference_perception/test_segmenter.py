import json

import numpy as np
import pytest

from lidar_quality_core.metrics import confusion_matrix, per_class_iou
from lidar_quality_core.model_store import ModelStoreError, load_model, manifest_path_for
from lidar_sim.classes import BUILDING, CAR, NUM_CLASSES, ROAD, UNLABELED, VEGETATION
from lidar_sim.frames import split_frames
from reference_perception.segmenter import (DEFAULT_MODEL_PATH, FEATURE_NAMES,
                                            ReferenceSegmenter, evaluate_segmenter,
                                            segmenter_features, train_segmenter)


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    # threaded BLAS on a busy 2-core machine slows the tiny training down ten-fold
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield


@pytest.fixture(scope="module")
def frame():
    """A held-out frame: first frame of a reference_test sequence."""
    return next(split_frames("reference_test", sequences=[0]))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A small segmenter trained on two frames of reference_train (a few seconds)."""
    path = tmp_path_factory.mktemp("seg") / "tiny.joblib"
    res = train_segmenter(path, sequences=[0, 1, 2], frames=1, val_sequences=[],
                          per_class=2000, hidden=(32,), epochs=12, learning_rate=3e-3,
                          test_split=None,
                          verbose=False)
    return path, res


def test_features_shape_dtype_finite(frame):
    X = segmenter_features(frame.xyz, frame.intensity, frame.ring)
    assert X.shape == (len(frame.xyz), len(FEATURE_NAMES)) and X.dtype == np.float32
    assert np.isfinite(X).all()
    assert len(set(FEATURE_NAMES)) == len(FEATURE_NAMES)
    # rings from the elevations give the same features as the ring field
    np.testing.assert_allclose(segmenter_features(frame.xyz, frame.intensity), X, atol=1e-5)


def test_features_do_not_depend_on_point_order(frame):
    rng = np.random.default_rng(0)
    sel = rng.choice(len(frame.xyz), 30_000, replace=False)  # a sparser cloud, faster
    xyz, inten, ring = frame.xyz[sel], frame.intensity[sel], frame.ring[sel]
    perm = rng.permutation(len(sel))
    for r in (ring, None):
        X = segmenter_features(xyz, inten, r)
        Xp = segmenter_features(xyz[perm], inten[perm], None if r is None else r[perm])
        np.testing.assert_array_equal(Xp, X[perm])


def test_height_feature_is_height_above_ground(frame):
    X = segmenter_features(frame.xyz, frame.intensity, frame.ring)
    h = X[:, FEATURE_NAMES.index("height")]
    road = frame.semantic == ROAD
    assert np.median(np.abs(h[road])) < 0.1
    assert np.median(h[frame.semantic == CAR]) > 0.5


def test_probabilities_sum_to_one(tiny, frame):
    seg = ReferenceSegmenter.load(tiny[0])
    P = seg.predict_proba(frame.xyz, frame.intensity, frame.ring)
    assert P.shape == (len(frame.xyz), NUM_CLASSES) and P.dtype == np.float32
    assert P.flags.c_contiguous
    assert (P >= 0).all() and (P <= 1).all()
    np.testing.assert_allclose(P.sum(axis=1), 1.0, atol=1e-5)
    # the fast float32 forward pass is the stored model's predict_proba
    X = segmenter_features(frame.xyz[:5000], frame.intensity[:5000], frame.ring[:5000])
    np.testing.assert_allclose(seg.predict_features(X), seg.model.predict_proba(X), atol=1e-4)
    # the simulator never labels points unlabeled: the model learnt to avoid it
    assert P[:, UNLABELED].mean() < 0.01


def test_empty_cloud(tiny):
    seg = ReferenceSegmenter.load(tiny[0])
    for xyz in (np.zeros((0, 3), np.float32), np.zeros(0)):
        P = seg.predict_proba(xyz, np.zeros(0))
        assert P.shape == (0, NUM_CLASSES) and P.dtype == np.float32
    assert segmenter_features(np.zeros((0, 3)), np.zeros(0)).shape == (0, len(FEATURE_NAMES))
    assert seg.predict(np.zeros((0, 3)), np.zeros(0)).shape == (0,)


def test_nan_points_get_the_uniform_distribution(tiny, frame):
    seg = ReferenceSegmenter.load(tiny[0])
    xyz, inten, ring = frame.xyz[:20_000].copy(), frame.intensity[:20_000].copy(), \
        frame.ring[:20_000]
    clean = seg.predict_proba(xyz, inten, ring)
    bad = np.zeros(len(xyz), bool)
    bad[[3, 500, 19_999]] = True
    xyz[3, 0] = np.nan
    xyz[500] = np.inf
    inten[19_999] = np.nan
    P = seg.predict_proba(xyz, inten, ring)
    np.testing.assert_allclose(P[bad], 1.0 / NUM_CLASSES)
    np.testing.assert_allclose(P.sum(axis=1), 1.0, atol=1e-5)
    assert (P[bad].argmax(axis=1) == UNLABELED).all()
    # the other points are classified as if the bad ones were not there
    keep = ~bad
    np.testing.assert_allclose(P[keep], seg.predict_proba(xyz[keep], inten[keep], ring[keep]),
                               atol=1e-6)
    assert (P[keep].argmax(1) == clean[keep].argmax(1)).mean() > 0.99
    allnan = seg.predict_proba(np.full((4, 3), np.nan), np.zeros(4))
    np.testing.assert_allclose(allnan, 1.0 / NUM_CLASSES)


def test_points_outside_the_field_of_view_are_classified(tiny, frame):
    seg = ReferenceSegmenter.load(tiny[0])
    xyz = np.r_[frame.xyz[:1000], [[10.0, 0.0, 8.0], [5.0, 5.0, -9.0]]].astype(np.float32)
    inten = np.r_[frame.intensity[:1000], [0.3, 0.3]].astype(np.float32)
    P = seg.predict_proba(xyz, inten)
    assert np.isfinite(P).all()
    np.testing.assert_allclose(P.sum(axis=1), 1.0, atol=1e-5)


def test_tiny_model_beats_chance_on_a_held_out_frame(tiny, frame):
    seg = ReferenceSegmenter.load(tiny[0])
    pred = seg.predict(frame.xyz, frame.intensity, frame.ring)
    cm = confusion_matrix(frame.semantic, pred, NUM_CLASSES, ignore=UNLABELED)
    iou = per_class_iou(cm)
    acc = np.trace(cm) / cm.sum()
    # chance: the majority class (road) is ~40 % of the points
    assert acc > 0.75, acc
    assert iou[ROAD] > 0.75 and iou[BUILDING] > 0.6 and iou[CAR] > 0.5, iou
    assert iou[VEGETATION] > 0.1, iou
    assert np.nanmean(iou[1:]) > 0.3, iou  # a random guess scores ~0.04


def test_manifest_and_schema_check(tiny):
    path, res = tiny
    man = json.loads(manifest_path_for(path).read_text())
    assert man["task"] == "multiclass" and man["feature_names"] == list(FEATURE_NAMES)
    assert man["classes"] == list(range(NUM_CLASSES)) and len(man["class_names"]) == NUM_CLASSES
    assert man["training_data"]["split"] == "reference_train"
    with pytest.raises(ModelStoreError, match="missing from model|extra in model"):
        load_model(path, expected_features=list(FEATURE_NAMES) + ["extra"],
                   expected_task="multiclass")


def test_evaluate_segmenter(tiny):
    ev = evaluate_segmenter(tiny[0], "reference_test", sequences=[0], frames=1)
    assert ev["n_frames"] == 1
    cm = np.asarray(ev["confusion"])
    assert cm.shape == (NUM_CLASSES, NUM_CLASSES) and cm[UNLABELED].sum() == 0
    assert ev["n_points"] == cm.sum()
    assert 0.2 < ev["miou"] <= 1.0 and ev["accuracy"] > 0.7
    assert "unlabeled" not in ev["per_class_iou"]


@pytest.mark.skipif(not DEFAULT_MODEL_PATH.exists(), reason="no shipped segmenter model")
def test_shipped_model(frame):
    seg = ReferenceSegmenter.load()
    man = json.loads(manifest_path_for(DEFAULT_MODEL_PATH).read_text())
    assert DEFAULT_MODEL_PATH.stat().st_size < 3e6
    assert 0.5 <= man["metrics"]["reference_test_miou"] <= 0.8
    pred = seg.predict(frame.xyz, frame.intensity, frame.ring)
    iou = per_class_iou(confusion_matrix(frame.semantic, pred, NUM_CLASSES, ignore=UNLABELED))
    assert iou[ROAD] > 0.8 and iou[BUILDING] > 0.8 and iou[CAR] > 0.8, iou
