import numpy as np
import pytest

from lidar_quality_core.metrics import confusion_matrix, mean_iou, per_class_iou


def test_confusion_matrix_counts_true_by_pred():
    cm = confusion_matrix([0, 1, 1, 2, 2, 2], [0, 1, 2, 2, 2, 1], 3)
    np.testing.assert_array_equal(cm, [[1, 0, 0], [0, 1, 1], [0, 1, 2]])
    assert cm.dtype == np.int64


def test_ignored_ground_truth_is_left_out_but_predicting_it_is_an_error():
    cm = confusion_matrix([0, 0, 1, 1], [1, 0, 0, 1], 2, ignore=0)
    np.testing.assert_array_equal(cm, [[0, 0], [1, 1]])


def test_iou_by_hand():
    # class 1: TP 1, FN 1 (-> 2), FP 1 (from 2): 1/3; class 2: TP 2, FN 1, FP 1: 2/4
    cm = confusion_matrix([1, 1, 2, 2, 2], [1, 2, 2, 2, 1], 3)
    iou = per_class_iou(cm)
    assert np.isnan(iou[0])  # neither true nor predicted
    np.testing.assert_allclose(iou[1:], [1 / 3, 0.5])
    assert mean_iou(cm) == pytest.approx((1 / 3 + 0.5) / 2)


def test_mean_iou_over_present_classes_only():
    # class 2 is predicted but never true: not in the mean; unlabeled ignored
    cm = confusion_matrix([0, 1, 1, 1], [2, 1, 1, 2], 3, ignore=0)
    assert per_class_iou(cm)[2] == 0.0
    assert mean_iou(cm, ignore=0) == pytest.approx(2 / 3)
    # the ignored class never enters the mean even if its row is non-zero
    cm2 = confusion_matrix([0, 1], [0, 1], 2)
    assert mean_iou(cm2, ignore=0) == 1.0
    assert mean_iou(cm2) == 1.0


def test_perfect_and_empty():
    y = np.array([1, 2, 3, 3])
    assert mean_iou(confusion_matrix(y, y, 4)) == 1.0
    cm = confusion_matrix([], [], 4)
    assert cm.sum() == 0 and np.isnan(mean_iou(cm))


def test_matches_sklearn():
    from sklearn.metrics import confusion_matrix as sk_cm, jaccard_score

    rng = np.random.default_rng(0)
    t = rng.integers(0, 5, 1000)
    p = np.where(rng.random(1000) < 0.6, t, rng.integers(0, 5, 1000))
    cm = confusion_matrix(t, p, 5)
    np.testing.assert_array_equal(cm, sk_cm(t, p, labels=range(5)))
    np.testing.assert_allclose(per_class_iou(cm), jaccard_score(t, p, average=None))


def test_bad_input_raises():
    with pytest.raises(ValueError, match="outside"):
        confusion_matrix([0, 5], [0, 1], 3)
    with pytest.raises(ValueError, match="outside"):
        confusion_matrix([0, 1], [0, -1], 3)
    with pytest.raises(ValueError, match="length"):
        confusion_matrix([0, 1], [0], 3)
    with pytest.raises(ValueError, match="integer"):
        confusion_matrix([0.5], [0], 3)
    with pytest.raises(ValueError, match="square"):
        per_class_iou(np.zeros((2, 3)))
