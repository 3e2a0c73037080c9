"""Tests for lidar_quality_core.nms (greedy rotated NMS with suppression map)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lidar_quality_core import iou as iou_mod
from lidar_quality_core.iou import iou_3d, iou_bev
from lidar_quality_core.nms import NMSResult, rotated_nms


def ref_nms(boxes, scores, thr, score_threshold=None, max_output=None, iou="bev",
            classes=None):
    """O(N^2) textbook greedy NMS on a dense IoU matrix."""
    n = len(boxes)
    m = (iou_bev if iou == "bev" else iou_3d)(boxes, boxes) if n else np.zeros((0, 0))
    sup = np.full(n, -1)
    cand = [i for i in range(n) if not np.isnan(scores[i])
            and (score_threshold is None or scores[i] >= score_threshold)]
    cand.sort(key=lambda i: (-scores[i], i))
    keep = []
    done = set()
    for i in cand:
        if i in done:
            continue
        if max_output is not None and len(keep) >= max_output:
            break
        keep.append(i)
        sup[i] = i
        done.add(i)
        for j in cand:
            if j not in done and m[i, j] > thr and (classes is None or classes[i] == classes[j]):
                sup[j] = i
                done.add(j)
    return np.array(keep, dtype=np.int64), sup


def row(x, y=0.0, l=2.0, w=1.0, yaw=0.0, z=0.0, h=1.0):
    return [x, y, z, l, w, h, yaw]


def check_partition(res: NMSResult, n):
    assert res.suppressed_by.shape == (n,)
    assert res.keep.dtype.kind == "i" and res.suppressed_by.dtype.kind == "i"
    kept = set(res.keep.tolist())
    assert len(kept) == len(res.keep)
    for j, s in enumerate(res.suppressed_by.tolist()):
        assert s == -1 or s in kept
        assert (s == j) == (j in kept)


def test_three_boxes_middle_suppresses():
    # A(0) and C(2) each overlap B(1) by IoU 1/3 but not each other; B has the top score.
    boxes = np.array([row(0.0), row(1.0), row(2.0)])  # shift by half length -> IoU 1/3
    res = rotated_nms(boxes, [0.5, 0.9, 0.6], 0.3)
    np.testing.assert_array_equal(res.keep, [1])
    np.testing.assert_array_equal(res.suppressed_by, [1, 1, 1])
    res = rotated_nms(boxes, [0.5, 0.9, 0.6], 0.4)  # nothing reaches 0.4
    np.testing.assert_array_equal(res.keep, [1, 2, 0])
    check_partition(res, 3)


def test_chain_suppressed_box_does_not_suppress():
    # A > B > C; A suppresses B, B would suppress C, but B is gone so C survives.
    boxes = np.array([row(0.0), row(1.0), row(2.0)])
    res = rotated_nms(boxes, [0.9, 0.8, 0.7], 0.3)
    np.testing.assert_array_equal(res.keep, [0, 2])
    np.testing.assert_array_equal(res.suppressed_by, [0, 0, 2])


def test_iou_equal_to_threshold_is_kept():
    # [0,2]x[0,1] contains [0,1]x[0,1]: IoU exactly 0.5
    boxes = np.array([row(1.0, 0.5, l=2.0), row(0.5, 0.5, l=1.0)])
    assert iou_bev(boxes, boxes)[0, 1] == 0.5
    np.testing.assert_array_equal(rotated_nms(boxes, [0.9, 0.8], 0.5).keep, [0, 1])
    np.testing.assert_array_equal(rotated_nms(boxes, [0.9, 0.8], 0.4999).keep, [0])


def test_score_threshold_and_max_output_give_minus_one():
    boxes = np.array([row(0.0), row(0.2), row(10.0), row(20.0), row(30.0), row(30.1)])
    scores = np.array([0.9, 0.8, 0.7, 0.05, 0.6, 0.5])
    res = rotated_nms(boxes, scores, 0.5, score_threshold=0.1)
    np.testing.assert_array_equal(res.keep, [0, 2, 4])
    np.testing.assert_array_equal(res.suppressed_by, [0, 0, 2, -1, 4, 4])
    res = rotated_nms(boxes, scores, 0.5, score_threshold=0.1, max_output=2)
    np.testing.assert_array_equal(res.keep, [0, 2])
    # 4 is beyond max_output, and so is what only it suppressed (5)
    np.testing.assert_array_equal(res.suppressed_by, [0, 0, 2, -1, -1, -1])
    res = rotated_nms(boxes, scores, 0.5, max_output=0)
    assert len(res.keep) == 0 and (res.suppressed_by == -1).all()
    check_partition(rotated_nms(boxes, scores, 0.5, max_output=1), 6)


def test_ties_broken_by_index_and_nan_scores_dropped():
    boxes = np.array([row(0.0), row(0.1), row(0.2), row(9.0)])
    res = rotated_nms(boxes, [0.5, 0.7, 0.7, np.nan], 0.5)
    np.testing.assert_array_equal(res.keep, [1])
    np.testing.assert_array_equal(res.suppressed_by, [1, 1, 1, -1])


def test_class_aware():
    boxes = np.array([row(0.0), row(0.1), row(0.2)])
    scores = [0.9, 0.8, 0.7]
    res = rotated_nms(boxes, scores, 0.5, classes=[1, 2, 1])
    np.testing.assert_array_equal(res.keep, [0, 1])
    np.testing.assert_array_equal(res.suppressed_by, [0, 1, 0])
    res = rotated_nms(boxes, scores, 0.5, classes=np.array(["car", "car", "ped"]))
    np.testing.assert_array_equal(res.keep, [0, 2])
    np.testing.assert_array_equal(rotated_nms(boxes, scores, 0.5).keep, [0])


def test_3d_mode_uses_height():
    boxes = np.array([row(0.0), row(0.0, z=5.0)])  # same footprint, disjoint in z
    np.testing.assert_array_equal(rotated_nms(boxes, [0.9, 0.8], 0.5).keep, [0])
    np.testing.assert_array_equal(rotated_nms(boxes, [0.9, 0.8], 0.5, iou="3d").keep, [0, 1])
    with pytest.raises(ValueError):
        rotated_nms(boxes, [0.9, 0.8], 0.5, iou="2d")


def test_invalid_inputs():
    assert len(rotated_nms(np.zeros((0, 7)), np.zeros(0), 0.5).keep) == 0
    with pytest.raises(ValueError):
        rotated_nms(np.zeros((2, 7)), np.zeros(3), 0.5)
    with pytest.raises(ValueError):
        rotated_nms(np.zeros((2, 7)), np.zeros(2), 0.5, classes=[1])
    # degenerate boxes never overlap anything: they survive on their own
    boxes = np.array([row(0.0), [0, 0, 0, 0, 0, 0, 0], row(0.05)])
    res = rotated_nms(boxes, [0.9, 0.95, 0.8], 0.5)
    np.testing.assert_array_equal(res.keep, [1, 0])
    np.testing.assert_array_equal(res.suppressed_by, [0, 1, 0])


def test_rotated_overlap_matters():
    # same centre, 90 degrees apart: IoU = 1 / 3 for a 2 x 1 box (cross shape: 1 / (2+2-1))
    boxes = np.array([row(0.0), row(0.0, yaw=np.pi / 2)])
    assert iou_bev(boxes, boxes)[0, 1] == pytest.approx(1 / 3)
    np.testing.assert_array_equal(rotated_nms(boxes, [0.9, 0.8], 0.3).keep, [0])
    np.testing.assert_array_equal(rotated_nms(boxes, [0.9, 0.8], 0.34).keep, [0, 1])


def test_synthetic_proposals_against_reference():
    from lidar_quality_core.synthetic import synthetic_frame
    f = synthetic_frame(n_points=1000, n_objects=20, n_proposals=200, seed=5)
    for thr in (0.1, 0.3, 0.5, 0.7):
        res = rotated_nms(f.proposals, f.prop_scores, thr)
        keep, sup = ref_nms(f.proposals, f.prop_scores, thr)
        np.testing.assert_array_equal(res.keep, keep)
        np.testing.assert_array_equal(res.suppressed_by, sup)
        check_partition(res, len(f.proposals))
    assert len(rotated_nms(f.proposals, f.prop_scores, 0.3).keep) < 100


def test_kdtree_path_same_result(monkeypatch):
    from lidar_quality_core.synthetic import synthetic_frame
    f = synthetic_frame(n_points=1000, n_objects=20, n_proposals=200, seed=6)
    a = rotated_nms(f.proposals, f.prop_scores, 0.4)
    monkeypatch.setattr(iou_mod, "_DENSE_PREFILTER_MAX", 0)
    b = rotated_nms(f.proposals, f.prop_scores, 0.4)
    np.testing.assert_array_equal(a.keep, b.keep)
    np.testing.assert_array_equal(a.suppressed_by, b.suppressed_by)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 40),
       thr=st.sampled_from([0.0, 0.1, 0.3, 0.5, 0.9]),
       score_threshold=st.sampled_from([None, 0.3]),
       max_output=st.sampled_from([None, 0, 1, 3, 10]),
       n_classes=st.sampled_from([0, 1, 3]), mode=st.sampled_from(["bev", "3d"]),
       tied=st.booleans())
def test_matches_reference_property(seed, n, thr, score_threshold, max_output, n_classes,
                                    mode, tied):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-4, 4, (max(n // 4, 1), 2))
    pick = rng.integers(0, len(centres), n)
    boxes = np.column_stack([centres[pick] + rng.normal(0, 0.4, (n, 2)), rng.normal(0, 0.3, n),
                             rng.uniform(0.5, 4, n), rng.uniform(0.5, 2, n),
                             rng.uniform(0.5, 2, n), rng.uniform(-np.pi, np.pi, n)])
    scores = rng.uniform(0, 1, n)
    if tied:
        scores = np.round(scores, 1)  # many exact ties
    classes = rng.integers(0, n_classes, n) if n_classes else None
    res = rotated_nms(boxes, scores, thr, score_threshold=score_threshold,
                      max_output=max_output, iou=mode, classes=classes)
    keep, sup = ref_nms(boxes, scores, thr, score_threshold, max_output, mode, classes)
    np.testing.assert_array_equal(res.keep, keep)
    np.testing.assert_array_equal(res.suppressed_by, sup)
    check_partition(res, n)
    # survivors are in non-increasing score order
    assert np.all(np.diff(scores[res.keep]) <= 0)
