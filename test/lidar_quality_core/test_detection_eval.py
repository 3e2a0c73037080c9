"""Tests for lidar_quality_core.detection_eval (matching, KITTI AP, LiDAR-MIMO partitions)."""
import math

import numpy as np
import pytest
from sklearn.metrics import precision_recall_curve

from lidar_quality_core.detection_eval import (KITTI_IOU_THRESHOLDS, FrameMatch, Partition,
                                               average_precision, evaluate, fp_partition,
                                               match_frame, partition_counts,
                                               precision_recall, summarize)
from lidar_quality_core.iou import iou_3d, iou_bev


def row(x, y=0.0, l=2.0, w=1.0, yaw=0.0, z=0.0, h=1.0):
    return [x, y, z, l, w, h, yaw]


def boxes(*rows):
    return np.array(rows, dtype=float).reshape(-1, 7)


def match(det, scores, labels, gt, gt_labels, thr=0.5, **kw):
    return match_frame(boxes(*det), scores, labels, boxes(*gt), gt_labels,
                       iou_threshold=thr, **kw)


# ---------------------------------------------------------------- independent references
def ref_ap(scores, tp, n_gt, levels):
    """Brute force: one operating point per distinct score threshold, plain Python."""
    pts = []
    for t in sorted(set(scores), reverse=True):
        acc = [k for k in range(len(scores)) if scores[k] >= t]
        n_tp = sum(1 for k in acc if tp[k])
        pts.append((n_tp / n_gt, n_tp / len(acc)))
    total = 0.0
    for r in levels:
        total += max([p for rec, p in pts if rec >= r - 1e-12], default=0.0)
    return total / len(levels)


R40 = [k / 40 for k in range(1, 41)]
R11 = [k / 10 for k in range(11)]


def ref_match(iou, scores, dl, gl, thr, ign):
    """Plain-Python greedy matching with the rules of the module docstring.

    ``thr[i]``: IoU threshold of detection ``i``.
    """
    n, m = iou.shape
    order = sorted(range(n), key=lambda i: (-scores[i], i))
    taken, det_gt, tp, ignored = set(), [-1] * n, [False] * n, [False] * n
    for i in order:
        ok = [j for j in range(m) if gl[j] == dl[i] and iou[i, j] >= thr[i]]
        free = [j for j in ok if not ign[j] and j not in taken]
        if free:
            j = max(free, key=lambda j: (iou[i, j], -j))
            taken.add(j)
            det_gt[i], tp[i] = j, True
        elif any(ign[j] for j in ok):
            det_gt[i] = max((j for j in ok if ign[j]), key=lambda j: (iou[i, j], -j))
            ignored[i] = True
    return det_gt, tp, ignored


# ------------------------------------------------------------------------------ AP
def test_perfect_detections_ap_one():
    gt = [row(0), row(5), row(10, l=0.8, w=0.6)]
    labels = ["car", "car", "pedestrian"]
    fm = match(gt, [0.9, 0.8, 0.7], labels, gt, labels, thr=KITTI_IOU_THRESHOLDS)
    assert fm.tp.all() and (fm.det_gt == [0, 1, 2]).all() and (fm.gt_det == [0, 1, 2]).all()
    np.testing.assert_array_equal(fm.iou_matched, 1.0)
    assert average_precision(fm) == 1.0
    assert average_precision(fm, recall_points=11) == 1.0
    res = evaluate([(boxes(*gt), [0.9, 0.8, 0.7], labels, boxes(*gt), labels)],
                   ["car", "pedestrian", "cyclist"], KITTI_IOU_THRESHOLDS, "3d")
    assert res["map"] == 1.0 and res["map_classes"] == ["car", "pedestrian"]
    assert math.isnan(res["per_class"]["cyclist"]["ap"])
    assert res["per_class"]["car"] == {"ap": 1.0, "n_gt": 2, "n_det": 2, "n_tp": 2, "n_fp": 0,
                                       "n_ignored": 0}


def test_known_curve_r40_r11():
    # ranks: TP FP TP TP FP, 4 GT -> (P, R) = (1, .25) (.5, .25) (2/3, .5) (.75, .75) (.6, .75)
    # interpolated: 1 for r <= .25, .75 for .25 < r <= .75, 0 above
    s = [0.9, 0.8, 0.7, 0.6, 0.5]
    tp = [1, 0, 1, 1, 0]
    assert average_precision(s, tp, 4) == pytest.approx((10 * 1 + 20 * 0.75) / 40)  # 0.625
    assert average_precision(s, tp, 4, recall_points=11) == pytest.approx(
        (3 * 1 + 5 * 0.75) / 11)  # r = 0, .1, .2 | .3 .. .7
    prec, rec, thr = precision_recall(s, tp, 4)
    np.testing.assert_allclose(prec, [1, 0.5, 2 / 3, 0.75, 0.6])
    np.testing.assert_allclose(rec, [0.25, 0.25, 0.5, 0.75, 0.75])
    np.testing.assert_array_equal(thr, s)


def test_recall_levels_are_exact():
    # recall 3/10 must reach the level 0.3 although 3 * 0.1 > 0.3 in floating point
    s, tp = [0.9, 0.8, 0.7], [1, 1, 1]
    assert average_precision(s, tp, 10, recall_points=11) == pytest.approx(4 / 11)
    assert average_precision(s, tp, 10) == pytest.approx(12 / 40)
    assert average_precision(s, tp, 10, recall_points=101) == pytest.approx(31 / 101)
    assert average_precision(s, tp, 10, recall_points=[0.3]) == 1.0


def test_ties_form_one_operating_point():
    # order inside a tie must not matter: both give precision .5 at recall 1
    assert average_precision([0.5, 0.5], [1, 0], 1) == 0.5
    assert average_precision([0.5, 0.5], [0, 1], 1) == 0.5
    assert average_precision([0.6, 0.5], [1, 0], 1) == 1.0


def test_ap_edge_cases():
    assert average_precision([], [], 3) == 0.0
    assert average_precision([], [], 3, recall_points=11) == 0.0
    assert math.isnan(average_precision([0.4], [0], 0))
    assert average_precision([0.4, 0.3], [0, 0], 2) == 0.0
    with pytest.raises(ValueError, match="NaN"):
        average_precision([0.4, np.nan], [1, 0], 2)
    with pytest.raises(ValueError, match="exceed"):
        average_precision([0.4, 0.3], [1, 1], 1)
    with pytest.raises(ValueError, match="boolean"):
        average_precision([0.4], [0.5], 1)
    with pytest.raises(ValueError, match="recall_points"):
        average_precision([0.4], [1], 1, recall_points=20)
    with pytest.raises(ValueError, match="n_gt"):
        average_precision([0.4], [1])


@pytest.mark.parametrize("seed", range(40))
def test_r40_matches_sklearn_curve_and_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    s = np.round(rng.random(n), int(rng.integers(1, 3)))  # coarse scores: many ties
    tp = rng.random(n) < rng.random()
    tp[rng.integers(n)] = True  # sklearn needs a positive
    n_gt = int(tp.sum() + rng.integers(0, 10))
    ours = average_precision(s, tp, n_gt)

    prec, rec, _ = precision_recall_curve(tp, s)
    prec, rec = prec[:-1], rec[:-1] * tp.sum() / n_gt  # drop sklearn's (1, 0) end point
    interp = [prec[rec >= r - 1e-12].max(initial=0.0) for r in np.arange(1, 41) / 40]
    assert ours == pytest.approx(np.mean(interp), abs=1e-12)
    assert ours == pytest.approx(ref_ap(list(s), list(tp), n_gt, R40), abs=1e-12)
    assert average_precision(s, tp, n_gt, recall_points=11) == pytest.approx(
        ref_ap(list(s), list(tp), n_gt, R11), abs=1e-12)
    # permuting the input (ties included) changes nothing
    p = rng.permutation(n)
    assert average_precision(s[p], tp[p], n_gt) == pytest.approx(ours, abs=1e-15)


# ------------------------------------------------------------------------ matching
def test_duplicate_is_fp_whatever_the_input_order():
    fm = match([row(0), row(0)], [0.8, 0.9], ["car", "car"], [row(0)], ["car"])
    np.testing.assert_array_equal(fm.tp, [False, True])
    np.testing.assert_array_equal(fm.fp, [True, False])
    np.testing.assert_array_equal(fm.det_gt, [-1, 0])
    np.testing.assert_array_equal(fm.gt_det, [1])
    assert fm.hit().all()  # LMD target: both overlap the object well
    np.testing.assert_array_equal(fp_partition(fm), [Partition.FP_ML, Partition.TP])
    np.testing.assert_array_equal(fp_partition(fm, separate_duplicates=True),
                                  [Partition.DUPLICATE, Partition.TP])
    assert average_precision(fm) == 1.0  # the FP comes after full recall


def test_lower_score_detection_takes_second_gt():
    # GT A at x=0, B at x=1. d0 (x=.4): IoU A 2/3, B .538 -> takes A although d1 fits A
    # better (.818); d1 (x=.2) then takes B (IoU .4286): free GT boxes stay available.
    gt, gl = [row(0), row(1)], ["car", "car"]
    fm = match([row(0.4), row(0.2)], [0.9, 0.8], ["car", "car"], gt, gl, thr=0.4)
    np.testing.assert_array_equal(fm.det_gt, [0, 1])
    np.testing.assert_array_equal(fm.gt_det, [0, 1])
    assert fm.tp.all()
    np.testing.assert_allclose(fm.iou_matched, [2 / 3, 3 / 7])
    np.testing.assert_allclose(fm.iou_same_class, [2 / 3, 9 / 11])
    # with 0.5, B is out of reach for d1: a duplicate of A
    fm = match([row(0.4), row(0.2)], [0.9, 0.8], ["car", "car"], gt, gl, thr=0.5)
    np.testing.assert_array_equal(fm.tp, [True, False])
    np.testing.assert_array_equal(fm.gt_det, [0, -1])
    assert fp_partition(fm, separate_duplicates=True)[1] == Partition.DUPLICATE


def test_class_mismatch_is_not_tp():
    fm = match([row(0)], [0.9], ["pedestrian"], [row(0)], ["car"])
    assert not fm.tp[0] and fm.fp[0] and fm.det_gt[0] == -1 and fm.gt_det[0] == -1
    assert fm.iou_same_class[0] == 0.0 and fm.iou_any[0] == 1.0 and fm.gt_any[0] == 0
    assert not fm.hit()[0] and fm.hit(class_aware=False)[0]
    assert fp_partition(fm)[0] == Partition.FP_ML


def test_integer_and_numpy_labels():
    fm = match([row(0), row(5)], [0.9, 0.8], np.array([1, 2]), [row(0), row(5)], [1, 1])
    np.testing.assert_array_equal(fm.tp, [True, False])
    fm = match([row(0)], [0.9], np.array(["car"]), [row(0)], ["car"])
    assert fm.tp[0]


def test_iou_threshold_boundary():
    v = iou_bev(boxes(row(0.5)), boxes(row(0)))[0, 0]  # 0.6
    assert v == pytest.approx(0.6)
    up, down = np.nextafter(v, 1.0), np.nextafter(v, 0.0)

    def tp(thr, strict=False):
        return bool(match([row(0.5)], [0.9], ["car"], [row(0)], ["car"], thr=thr,
                          strict=strict).tp[0])

    assert tp(v) and not tp(up)  # IoU >= t by default (LMD)
    assert not tp(v, strict=True) and tp(down, strict=True)  # IoU > t (KITTI devkit)
    assert tp(1.0) is False and match([row(0)], [1], ["car"], [row(0)], ["car"], thr=1.0).tp[0]
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="threshold"):
            tp(bad)


def test_per_class_thresholds_kitti():
    # IoU 0.6 for each pair: enough for pedestrian / cyclist (0.5), not for car (0.7)
    ped = dict(l=0.8, w=0.6)
    det = [row(0.5), row(20.2, **ped), row(40.2, **ped)]
    gt = [row(0), row(20, **ped), row(40, **ped)]
    iou = np.diag(iou_bev(boxes(*det), boxes(*gt)))
    np.testing.assert_allclose(iou, [0.6, 0.6, 0.6])
    labels = ["car", "pedestrian", "cyclist"]
    fm = match(det, [0.9, 0.8, 0.7], labels, gt, labels, thr=KITTI_IOU_THRESHOLDS)
    np.testing.assert_array_equal(fm.tp, [False, True, True])
    np.testing.assert_array_equal(fm.threshold, [0.7, 0.5, 0.5])
    res = summarize([fm], ["car", "pedestrian", "cyclist"])
    assert [res["per_class"][c]["ap"] for c in labels] == [0.0, 1.0, 1.0]
    assert res["map"] == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="'van'"):
        match(det, [0.9, 0.8, 0.7], ["car", "van", "cyclist"], gt, labels,
              thr=KITTI_IOU_THRESHOLDS)


def test_ignored_gt():
    # GT 0 counts, GT 1 (same class) is ignored, e.g. a don't-care region
    gt, gl, ign = [row(0), row(10)], ["car", "car"], [False, True]
    det = [row(10), row(0), row(10.1)]
    fm = match(det, [0.9, 0.5, 0.95], ["car"] * 3, gt, gl, gt_ignore=ign)
    np.testing.assert_array_equal(fm.ignored, [True, False, True])  # absorbs both
    np.testing.assert_array_equal(fm.tp, [False, True, False])
    np.testing.assert_array_equal(fm.fp, [False, False, False])
    np.testing.assert_array_equal(fm.det_gt, [1, 0, 1])
    np.testing.assert_array_equal(fm.gt_det, [1, -1])
    assert fm.n_gt == 1
    assert average_precision(fm) == 1.0  # the high-scored ignored boxes are left out
    np.testing.assert_array_equal(fp_partition(fm), [Partition.IGNORED, Partition.TP,
                                                     Partition.IGNORED])
    # without the ignore region the same boxes are FPs ranked first
    fm2 = match(det, [0.9, 0.5, 0.95], ["car"] * 3, [row(0)], ["car"])
    assert average_precision(fm2) == pytest.approx(1 / 3)
    res = summarize([fm])
    assert res["per_class"]["car"] == {"ap": 1.0, "n_gt": 1, "n_det": 3, "n_tp": 1,
                                       "n_fp": 0, "n_ignored": 2}


def test_non_ignored_gt_preferred_over_ignored():
    # the ignored GT overlaps the detection more, the real one still wins
    fm = match([row(0.2)], [0.9], ["car"], [row(0), row(0.2)], ["car", "car"],
               gt_ignore=[False, True])
    assert fm.tp[0] and fm.det_gt[0] == 0 and not fm.ignored[0]


def test_3d_mode_uses_height_overlap():
    det, gt = [row(0, z=0.5)], [row(0)]
    assert match(det, [0.9], ["car"], gt, ["car"], thr=0.7, mode="bev").tp[0]
    fm = match(det, [0.9], ["car"], gt, ["car"], thr=0.7, mode="3d")
    assert not fm.tp[0]
    assert fm.iou_any[0] == pytest.approx(1 / 3)  # z overlap .5 of height 1
    with pytest.raises(ValueError, match="mode"):
        match(det, [0.9], ["car"], gt, ["car"], mode="2d")


def test_match_edge_cases():
    fm = match([], [], [], [row(0)], ["car"])
    assert len(fm.tp) == 0 and (fm.gt_det == -1).all() and fm.n_gt == 1
    assert average_precision(fm) == 0.0
    fm = match([row(0), row(3)], [0.9, 0.8], ["car", "car"], [], [])
    assert not fm.tp.any() and fm.fp.all() and (fm.det_gt == -1).all()
    assert (fm.iou_any == 0).all() and (fm.gt_any == -1).all()
    assert math.isnan(average_precision(fm))
    np.testing.assert_array_equal(fp_partition(fm), [Partition.FP_BG] * 2)
    fm = match([], [], [], [], [])
    assert len(fm.tp) == 0 and len(fm.gt_det) == 0
    with pytest.raises(ValueError, match="NaN"):
        match([row(0)], [np.nan], ["car"], [row(0)], ["car"])
    with pytest.raises(ValueError, match="det_scores"):
        match([row(0)], [0.5, 0.4], ["car"], [row(0)], ["car"])
    with pytest.raises(ValueError, match="det_labels"):
        match([row(0)], [0.5], [], [row(0)], ["car"])
    with pytest.raises(ValueError, match="gt_ignore"):
        match([row(0)], [0.5], ["car"], [row(0)], ["car"], gt_ignore=[True, False])
    with pytest.raises(ValueError, match="shape"):
        match_frame(np.zeros((1, 6)), [0.5], ["car"], boxes(row(0)), ["car"], iou_threshold=0.5)


def test_equal_scores_match_in_input_order():
    fm = match([row(0.1), row(0)], [0.7, 0.7], ["car", "car"], [row(0)], ["car"])
    np.testing.assert_array_equal(fm.tp, [True, False])  # not the better-fitting second


@pytest.mark.parametrize("seed", range(25))
def test_matching_matches_plain_python_reference(seed):
    rng = np.random.default_rng(100 + seed)
    m, n = int(rng.integers(0, 8)), int(rng.integers(0, 12))
    gt = np.column_stack([rng.uniform(-4, 4, (m, 2)), rng.uniform(-0.3, 0.3, m),
                          rng.uniform(1, 3, m), rng.uniform(0.5, 1.5, m),
                          rng.uniform(1, 2, m), rng.uniform(-3, 3, m)])
    src = rng.integers(0, max(m, 1), n)
    det = (gt[src] if m else np.zeros((n, 7)) + [0, 0, 0, 2, 1, 1, 0]) + \
        rng.normal(0, 0.4, (n, 7)) * [1, 1, 0.2, 0.2, 0.1, 0.1, 0.2]
    det[:, 3:6] = np.abs(det[:, 3:6]) + 0.1
    scores = np.round(rng.random(n), 1)
    classes = np.array(["car", "ped"])
    gl, dl = classes[rng.integers(0, 2, m)], classes[rng.integers(0, 2, n)]
    ign = rng.random(m) < 0.25
    thr = {"car": 0.4, "ped": 0.25}
    fm = match_frame(det, scores, dl, gt, gl, iou_threshold=thr, gt_ignore=ign, mode="3d")
    iou = iou_3d(det, gt)
    det_gt, tp, ignored = ref_match(iou, scores, list(dl), list(gl), [thr[c] for c in dl], ign)
    np.testing.assert_array_equal(fm.det_gt, det_gt)
    np.testing.assert_array_equal(fm.tp, tp)
    np.testing.assert_array_equal(fm.ignored, ignored)
    for j in range(m):
        expect = [i for i in range(n) if tp[i] and det_gt[i] == j]
        assert fm.gt_det[j] == (expect[0] if expect else -1)
    same = dl[:, None] == gl[None, :]
    np.testing.assert_allclose(fm.iou_same_class, np.where(same, iou, 0).max(1, initial=0))
    np.testing.assert_allclose(fm.iou_any, iou.max(1, initial=0))


# ----------------------------------------------------------------------- partitions
def test_fp_partition_hand_built():
    gt, gl = [row(0), row(30)], ["car", "car"]
    det = [row(0),            # TP
           row(1.5),          # IoU 1/7 > 0.1: mis-localized
           row(1.9),          # IoU 0.0256: background
           row(15),           # no overlap: background
           row(0),            # duplicate of the TP
           row(30.3)]         # hits the ignored GT box
    labels = ["car"] * 6
    det_ped = row(0.2)        # pedestrian on the car: misclassified
    fm = match(det + [det_ped], [0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3], labels + ["pedestrian"],
               gt, gl, thr={"car": 0.7, "pedestrian": 0.5}, gt_ignore=[False, True])
    P = Partition
    np.testing.assert_array_equal(
        fp_partition(fm), [P.TP, P.FP_ML, P.FP_BG, P.FP_BG, P.FP_ML, P.IGNORED, P.FP_ML])
    np.testing.assert_array_equal(
        fp_partition(fm, separate_duplicates=True),
        [P.TP, P.FP_ML, P.FP_BG, P.FP_BG, P.DUPLICATE, P.IGNORED, P.FP_ML])
    np.testing.assert_allclose(fm.iou_any[:4], [1, 1 / 7, 0.1 / 3.9, 0])
    np.testing.assert_array_equal(fm.gt_any, [0, 0, 0, -1, 0, 1, 0])
    assert partition_counts(fm) == {"IGNORED": 1, "TP": 1, "FP_ML": 3, "FP_BG": 2,
                                    "DUPLICATE": 0}
    assert partition_counts([fm, fm], separate_duplicates=True) == {
        "IGNORED": 2, "TP": 2, "FP_ML": 4, "FP_BG": 4, "DUPLICATE": 2}


def test_fp_partition_bg_boundary():
    # exactly at the background IoU: background (authors' code: BG iff not IoU > 0.1)
    v = iou_bev(boxes(row(1.5)), boxes(row(0)))[0, 0]
    fm = match([row(1.5)], [0.9], ["car"], [row(0)], ["car"], thr=0.7)
    assert fp_partition(fm, bg_iou=v)[0] == Partition.FP_BG
    assert fp_partition(fm, bg_iou=np.nextafter(v, 0))[0] == Partition.FP_ML
    # a background box of another class than every GT box is still background
    fm = match([row(1.9)], [0.9], ["pedestrian"], [row(0)], ["car"], thr=0.5)
    assert fp_partition(fm)[0] == Partition.FP_BG


# ------------------------------------------------------------------------ summaries
def test_evaluate_several_frames_and_inputs():
    f1 = dict(det_boxes=boxes(row(0), row(5)), det_scores=[0.9, 0.3],
              det_labels=["car", "car"], gt_boxes=boxes(row(0)), gt_labels=["car"])
    f2 = (boxes(row(0)), [0.6], ["car"], boxes(row(0), row(9)), ["car", "car"])
    res = evaluate([f1, f2], ["car"], 0.7, "bev")
    # ranks over both frames: .9 TP, .6 TP, .3 FP; 3 GT -> P = 1 up to recall 2/3
    assert res["per_class"]["car"]["ap"] == pytest.approx(26 / 40)
    assert res["per_class"]["car"]["n_gt"] == 3 and res["per_class"]["car"]["n_fp"] == 1
    assert res["map"] == pytest.approx(26 / 40)
    assert len(res["matches"]) == 2 and isinstance(res["matches"][0], FrameMatch)
    assert average_precision(res["matches"], label="car") == res["map"]
    r11 = evaluate([f1, f2], ["car"], 0.7, recall_points=11)
    assert r11["map"] == pytest.approx(7 / 11)  # r = 0 .. 0.6
    with pytest.raises(ValueError, match="unknown frame keys"):
        evaluate([dict(f1, extra=1)], ["car"], 0.7)
    with pytest.raises(ValueError, match="5 or 6"):
        evaluate([f2[:4]], ["car"], 0.7)


def test_summarize_default_classes_and_empty_map():
    fm = match([row(0)], [0.9], ["car"], [], [])
    res = summarize([fm])
    assert list(res["per_class"]) == ["car"] and math.isnan(res["map"])
    assert res["map_classes"] == []
    assert math.isnan(summarize([])["map"])
