"""Tests for lidar_quality_core.lmd.features (LidarMetaDetect box-wise features)."""
import math

import numpy as np
import pytest

from lidar_quality_core.iou import iou_3d, iou_bev
from lidar_quality_core.nms import rotated_nms
from lidar_quality_core.lmd.features import (OWN_QUANTITIES, SET_QUANTITIES, ProposalSets, compute_features,
                                             feature_names)

STATS = ("min", "max", "mean", "std")


def col(x, name, mode="threshold", extra=None):
    return x[:, feature_names(mode, extra).index(name)]


def row(x, k, mode="threshold"):
    return dict(zip(feature_names(mode), x[k]))


def box(x=0.0, y=0.0, z=0.0, l=4.0, w=2.0, h=2.0, yaw=0.0):
    return [x, y, z, l, w, h, yaw]


def pstd(v):
    v = np.asarray(v, dtype=float)
    return float(np.sqrt(np.mean((v - v.mean()) ** 2)))


# ---------------------------------------------------------------- independent reference
def ref_inside(points, b):
    """Brute-force membership of one box via an explicit rotation matrix."""
    x, y, z, l, w, h, yaw = b
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    with np.errstate(invalid="ignore"):
        loc = (points[:, :2] - [x, y]) @ rot
        return ((np.abs(loc[:, 0]) <= l / 2) & (np.abs(loc[:, 1]) <= w / 2)
                & (np.abs(points[:, 2] - z) <= h / 2))


def ref_quantities(points, inten, b, score, n_valid):
    ok = np.isfinite(points).all(axis=1) & np.isfinite(inten)
    r = inten[ok & ref_inside(points, b)].astype(float)
    r = r if len(r) else np.zeros(1)  # authors: statistics of [0] for an empty box
    x, y, z, l, w, h, yaw = b
    vol, surf = l * w * h, 2 * (l * w + l * h + w * h)
    p = float(np.sum(ok & ref_inside(points, b)))
    return dict(x=x, y=y, z=z, l=l, w=w, h=h, theta=(yaw + math.pi) % (2 * math.pi) - math.pi,
                score=score, volume=vol, surface=surf, size_ratio=vol / surf, points=p,
                points_frac=p / n_valid, refl_max=r.max(), refl_mean=r.mean(), refl_std=r.std())


def ref_features(points, inten, boxes, scores, labels, pboxes, pscores, mode, sets=None,
                 t=0.5):
    """Loop-based features; IoUs from the core's dense iou_bev / iou_3d."""
    n_valid = int(np.sum(np.isfinite(points).all(axis=1) & np.isfinite(inten)))
    bev = iou_bev(boxes, pboxes) if len(pboxes) else np.zeros((len(boxes), 0))
    i3d = iou_3d(boxes, pboxes) if len(pboxes) else np.zeros((len(boxes), 0))
    out = []
    for k, b in enumerate(boxes):
        own = ref_quantities(points, inten, b, scores[k], n_valid)
        f = [own[q] for q in OWN_QUANTITIES if q != "class"]
        f.insert(OWN_QUANTITIES.index("class"), float(labels[k]))
        if mode != "none":
            mem = list(sets[k]) if mode == "exact" else list(np.flatnonzero(bev[k] > t))
            # the box itself among the proposals: its geometry and its score
            tol = 1e-6 * max(1.0, abs(scores[k]))
            same = [j for j in mem
                    if i3d[k, j] >= 1 - 1e-6 and abs(pscores[j] - scores[k]) <= tol]
            if same:
                mem.remove(min(same, key=lambda j: (abs(pscores[j] - scores[k]), -i3d[k, j],
                                                    pscores[j], *pboxes[j])))
            qs = [own] + [ref_quantities(points, inten, pboxes[j], pscores[j], n_valid)
                          for j in mem]
            for q in SET_QUANTITIES:
                v = np.array([d[q] for d in qs])
                if q == "theta":
                    v = own["theta"] + (v - own["theta"] + math.pi) % (2 * math.pi) - math.pi
                f += [v.min(), v.max(), v.mean(), v.std()]
            for vals in ([i3d[k, j] for j in mem if mode == "exact" or i3d[k, j] > t],
                         [bev[k, j] for j in mem]):
                v = np.array(vals) if vals else np.zeros(1)
                f += [v.min(), v.max(), v.mean(), v.std()]
            f.append(1.0 + len(mem))
        out.append(f)
    return np.array(out, dtype=float).reshape(len(boxes), -1)


# ---------------------------------------------------------------- schema
def test_schema():
    full = feature_names("exact")
    assert len(full) == 90 and len(set(full)) == 90
    assert feature_names("threshold") == full
    assert full[:17] == OWN_QUANTITIES and len(SET_QUANTITIES) == 16
    assert "class" not in SET_QUANTITIES
    assert full[17:21] == ("prop_x_min", "prop_x_max", "prop_x_mean", "prop_x_std")
    assert full[81:] == ("iou_3d_min", "iou_3d_max", "iou_3d_mean", "iou_3d_std",
                         "iou_bev_min", "iou_bev_max", "iou_bev_mean", "iou_bev_std",
                         "n_proposals")
    assert feature_names("none") == OWN_QUANTITIES
    assert feature_names("exact", ["car", "ped"])[-2:] == ("class_score_car",
                                                            "class_score_ped")
    assert len(feature_names("none", 3)) == 20
    with pytest.raises(ValueError):
        feature_names("bogus")


# ---------------------------------------------------------------- hand-built frame
# Box b: centre 0, 4 x 2 x 2, axis aligned. Proposals (all 4 x 2 x 2 unless stated):
#   0: b itself (the detector publishes its survivor among the proposals)
#   1: x + 1            -> BEV overlap 3 x 2 = 6: IoU_BEV = 6 / 10 = 0.6, IoU_3D = 0.6
#   2: x + 0.5, z + 0.5 -> IoU_BEV = 7 / 9, IoU_3D = 10.5 / 21.5 (< 0.5)
#   3: x + 2            -> IoU_BEV = 4 / 12 (not a member)
#   4: 2 x 2 x 2 at 0   -> IoU_BEV = 4 / 8 = 0.5 exactly: not a member (strictly above t)
#   5: far away
PROPS = np.array([box(), box(x=1), box(x=0.5, z=0.5), box(x=2), box(l=2), box(x=30, y=30)])
PSCORES = np.array([0.9, 0.5, 0.7, 0.6, 0.4, 0.3])
# Points (z = 0 unless stated) with their reflectance:
#   A (-1.75, 0) 0.2: b only         B (0, 0) 0.4: b, 1, 2, 4     C (1.9, .5) 0.6: b, 1, 2
#   D (2.4, 0) 1.0: 1, 2             E (2.8, 0) 0.8: 1            F (10, 10) 0.5: none
#   plus a NaN point and a point with NaN intensity, both ignored (also in |X| = 6)
POINTS = np.array([[-1.75, 0, 0], [0, 0, 0], [1.9, 0.5, 0], [2.4, 0, 0], [2.8, 0, 0],
                   [10, 10, 0], [np.nan, 0, 0], [0.5, 0, 0]])
INTEN = np.array([0.2, 0.4, 0.6, 1.0, 0.8, 0.5, 0.3, np.nan])


def hand_features(mode="threshold", **kw):
    return compute_features(POINTS, INTEN, np.array([box()]), [0.9], [2],
                            proposals=(PROPS, PSCORES), mode=mode, **kw)


def test_own_box_features_known_answers():
    f = row(compute_features(POINTS, INTEN, np.array([box(yaw=0.25)]), [0.9], [2],
                             mode="none"), 0, "none")
    exp = dict(x=0, y=0, z=0, l=4, w=2, h=2, theta=0.25, score=0.9, volume=16, surface=40,
               size_ratio=0.4, points=3, points_frac=3 / 6, refl_max=0.6, refl_mean=0.4,
               refl_std=math.sqrt(0.08 / 3))
    exp["class"] = 2
    assert set(f) == set(exp)
    for k, v in exp.items():
        assert f[k] == pytest.approx(v, abs=1e-12), k


def test_proposal_set_features_known_answers():
    f = row(hand_features(), 0)
    # members: b (itself, once), proposals 1 and 2
    assert f["n_proposals"] == 3
    members = {  # quantity -> values over (b, 1, 2)
        "x": [0, 1, 0.5], "y": [0, 0, 0], "z": [0, 0, 0.5], "l": [4] * 3, "w": [2] * 3,
        "h": [2] * 3, "theta": [0] * 3, "score": [0.9, 0.5, 0.7], "volume": [16] * 3,
        "surface": [40] * 3, "size_ratio": [0.4] * 3, "points": [3, 4, 3],
        "points_frac": [3 / 6, 4 / 6, 3 / 6], "refl_max": [0.6, 1.0, 1.0],
        "refl_mean": [0.4, 0.7, 2 / 3],
        "refl_std": [math.sqrt(0.08 / 3), math.sqrt(0.05), pstd([0.4, 0.6, 1.0])]}
    assert set(members) == set(SET_QUANTITIES)
    for q, v in members.items():
        for s, e in zip(STATS, (min(v), max(v), np.mean(v), pstd(v))):
            assert f[f"prop_{q}_{s}"] == pytest.approx(e, abs=1e-12), (q, s)
    bev = [0.6, 7 / 9]
    for s, e in zip(STATS, (0.6, 7 / 9, np.mean(bev), pstd(bev))):
        assert f[f"iou_bev_{s}"] == pytest.approx(e, abs=1e-12), s
    # IoU_3D statistics over the members with IoU_3D > t: proposal 1 only
    for s, e in zip(STATS, (0.6, 0.6, 0.6, 0.0)):
        assert f[f"iou_3d_{s}"] == pytest.approx(e, abs=1e-12), s


def test_threshold_is_strict_and_adjustable():
    assert col(hand_features(iou_threshold=0.5), "n_proposals")[0] == 3
    # proposal 4 has IoU_BEV exactly 0.5: in once the threshold is below it
    assert col(hand_features(iou_threshold=0.49), "n_proposals")[0] == 4
    assert col(hand_features(iou_threshold=0.7), "n_proposals")[0] == 2  # only proposal 2
    assert col(hand_features(iou_threshold=0.3), "n_proposals")[0] == 5  # + proposal 3


def test_self_copy_counted_once():
    """Survivor among the proposals or not: same features."""
    with_copy = hand_features()
    without = compute_features(POINTS, INTEN, np.array([box()]), [0.9], [2],
                               proposals=(PROPS[1:], PSCORES[1:]), mode="threshold")
    np.testing.assert_array_equal(with_copy, without)


# Issue 14 (2): box score 0.9; proposals b at 0.4, b at 0.9 (the survivor), b shifted at 0.6
DUP_PROPS = np.array([box(), box(), box(x=1)])
DUP_SCORES = np.array([0.4, 0.9, 0.6])


@pytest.mark.parametrize("mode", ["threshold", "exact"])
def test_self_copy_is_the_proposal_with_the_box_score(mode):
    """The same-geometry proposal at 0.4 is another member, whichever comes first (we
    used to drop the first one listed: score min 0.6, mean 0.8)."""
    runs = []
    for perm in ([0, 1, 2], [1, 0, 2], [2, 0, 1], [2, 1, 0]):
        perm = np.array(perm)
        inv = np.argsort(perm)  # new index of old proposal j
        runs.append(compute_features(POINTS, INTEN, np.array([box()]), [0.9], [2],
                                     proposals=(DUP_PROPS[perm], DUP_SCORES[perm]),
                                     mode=mode, preimage=[sorted(inv.tolist())]))
    f = row(runs[0], 0, mode)
    assert f["n_proposals"] == 3
    assert f["prop_score_min"] == 0.4 and f["prop_score_max"] == 0.9
    assert f["prop_score_mean"] == pytest.approx((0.9 + 0.4 + 0.6) / 3, abs=1e-15)
    assert f["prop_score_std"] == pytest.approx(pstd([0.9, 0.4, 0.6]), abs=1e-15)
    # IoU statistics over the two other members: the 0.4 copy (IoU 1) and the shifted box
    assert [f[f"iou_bev_{s}"] for s in STATS] == pytest.approx([0.6, 1.0, 0.8, 0.2])
    for x in runs[1:]:
        np.testing.assert_array_equal(x, runs[0])


def test_no_proposal_with_the_box_score_drops_nothing():
    """The survivor not published, a same-geometry proposal at another score: a member."""
    f = row(compute_features(POINTS, INTEN, np.array([box()]), [0.9], [2],
                             proposals=(DUP_PROPS[[0, 2]], DUP_SCORES[[0, 2]]),
                             mode="threshold"), 0)
    assert f["n_proposals"] == 3 and f["prop_score_min"] == 0.4
    assert f["prop_score_mean"] == pytest.approx((0.9 + 0.4 + 0.6) / 3, abs=1e-15)


def test_self_copy_after_a_float32_round_trip():
    b = np.array([box(x=12.3456789, y=-7.654321, z=0.123, l=4.21, w=1.87, h=1.53, yaw=0.321)])
    props = np.vstack([b.astype(np.float32).astype(float), b + [0.5, 0, 0, 0, 0, 0, 0]])
    score = 0.812345678901
    x = compute_features(POINTS, INTEN, b, [score], [2], mode="threshold",
                         proposals=(props, [float(np.float32(score)), 0.5]))
    y = compute_features(POINTS, INTEN, b, [score], [2], mode="threshold",
                         proposals=(props[1:], [0.5]))
    assert col(x, "n_proposals")[0] == 2
    np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6)


def _shuffled_frame(seed):
    """A random frame whose proposals hold the detections (same scores), copies of some
    detections at other scores and jittered proposals; exact-mode survivors of NMS."""
    pts, inten, dets, sc, lab, props, psc = random_frame(seed, n_obj=8, n_prop=60)
    rng = np.random.default_rng(seed + 1000)
    twin = rng.choice(len(dets), 3, replace=False)
    props = np.vstack([props, dets, dets[twin], dets[twin[:1]]])
    psc = np.r_[psc, sc, rng.random(3), sc[twin[0]]]  # the last: an exact duplicate
    return pts, inten, dets, sc, lab, props, psc, rng


@pytest.mark.parametrize("seed", range(12))
def test_features_do_not_depend_on_the_proposal_order(seed):
    """Shuffled proposals (and pre-images renumbered to match) give bit-identical
    features, in both modes, and the loop reference's values."""
    pts, inten, dets, sc, lab, props, psc, rng = _shuffled_frame(seed)
    nms = rotated_nms(props, psc, 0.3)
    pre = [np.r_[k, np.flatnonzero(nms.suppressed_by == k)] for k in nms.keep]
    cases = {"threshold": (dets, sc, lab, None),
             "exact": (props[nms.keep], psc[nms.keep], np.zeros(len(nms.keep), int), pre)}
    for mode, (b, s, lb, sets) in cases.items():
        runs = []
        for trial in range(6):
            perm = np.arange(len(props)) if trial == 0 else rng.permutation(len(props))
            inv = np.argsort(perm)
            kw = {} if sets is None else dict(preimage=[rng.permutation(inv[m]) for m in sets])
            runs.append(compute_features(pts, inten, b, s, lb, proposals=(props[perm], psc[perm]),
                                         mode=mode, **kw))
        for x in runs[1:]:
            np.testing.assert_array_equal(x, runs[0], err_msg=mode)
        ref = ref_features(pts, inten, b, s, lb, props, psc, mode, sets=sets)
        np.testing.assert_allclose(runs[0], ref, rtol=1e-9, atol=1e-9, err_msg=mode)


def test_exact_mode_known_answers():
    # pre-image {0 (the survivor itself), 1, 3}: proposal 3 is in although IoU 1/3
    f = row(hand_features("exact", preimage=[[0, 1, 3]]), 0)
    assert f["n_proposals"] == 3
    assert f["prop_x_min"] == 0 and f["prop_x_max"] == 2 and f["prop_x_mean"] == 1
    # exact mode: IoU_3D over all other members, no threshold
    for name in ("iou_3d", "iou_bev"):
        assert f[f"{name}_min"] == pytest.approx(1 / 3)
        assert f[f"{name}_max"] == pytest.approx(0.6)
        assert f[f"{name}_mean"] == pytest.approx((0.6 + 1 / 3) / 2)
        assert f[f"{name}_std"] == pytest.approx((0.6 - 1 / 3) / 2)
    as_sets = hand_features("exact", preimage=ProposalSets.from_lists([[0, 1, 3]]))
    np.testing.assert_array_equal(as_sets, hand_features("exact", preimage=[[1, 3]]))


def test_exact_vs_threshold_differ():
    """Proposal q overlaps both survivors (> t) but only the first one suppressed it."""
    b1, b2, q = box(), box(x=2.4), box(x=1.2)   # IoU(b1, q) = IoU(b2, q) = 5.6 / 10.4
    props = np.array([b1, b2, q])
    pscores = np.array([0.9, 0.8, 0.5])
    nms = rotated_nms(props, pscores, 0.5)
    assert nms.keep.tolist() == [0, 1]
    sets = ProposalSets.from_nms(nms.suppressed_by, nms.keep)
    assert [sorted(sets.index[sets.offsets[k]:sets.offsets[k + 1]]) for k in range(2)] == \
        [[0, 2], [1]]
    pts = np.array([[1.0, 0, 0], [3.0, 0.5, 0.5]])
    args = (pts, np.array([0.3, 0.7]), props[nms.keep], pscores[nms.keep], [0, 0])
    ex = compute_features(*args, proposals=(props, pscores), mode="exact", preimage=sets)
    th = compute_features(*args, proposals=(props, pscores), mode="threshold")
    assert col(ex, "n_proposals").tolist() == [2, 1]
    assert col(th, "n_proposals").tolist() == [2, 2]
    np.testing.assert_array_equal(ex[0], th[0])
    assert col(ex, "iou_bev_max")[1] == 0 and col(th, "iou_bev_max")[1] == pytest.approx(
        5.6 / 10.4)


# ---------------------------------------------------------------- special cases
def test_empty_box_has_finite_zero_point_features():
    x = compute_features(POINTS, INTEN, np.array([box(x=-20)]), [0.5], [0],
                         proposals=(PROPS, PSCORES), mode="threshold")
    f = row(x, 0)
    assert np.isfinite(x).all()
    for k in ("points", "points_frac", "refl_max", "refl_mean", "refl_std",
              "prop_points_max", "prop_refl_max_max"):
        assert f[k] == 0, k


def test_no_proposals_and_single_member():
    """No proposals (or only the box itself): N = 1, statistics = own values, std 0,
    IoU statistics 0 (authors)."""
    b = np.array([box(yaw=0.3)])
    runs = [compute_features(POINTS, INTEN, b, [0.9], [2], proposals=None, mode=m)
            for m in ("threshold", "exact")]
    runs.append(compute_features(POINTS, INTEN, b, [0.9], [2],
                                 proposals=(np.zeros((0, 7)), np.zeros(0)), mode="threshold"))
    runs.append(compute_features(POINTS, INTEN, b, [0.9], [2],
                                 proposals=(b, [0.9]), mode="exact", preimage=[[0]]))
    own = compute_features(POINTS, INTEN, b, [0.9], [2], mode="none")[0]
    for x in runs:
        f = row(x, 0)
        assert f["n_proposals"] == 1
        for q in SET_QUANTITIES:
            v = own[OWN_QUANTITIES.index(q)]
            assert [f[f"prop_{q}_{s}"] for s in STATS] == [v, v, v, 0.0], q
        assert all(f[f"{i}_{s}"] == 0 for i in ("iou_3d", "iou_bev") for s in STATS)
        np.testing.assert_array_equal(x[0, :17], own)


def test_one_other_proposal_statistics():
    f = row(compute_features(POINTS, INTEN, np.array([box()]), [0.9], [2],
                             proposals=(PROPS[1:2], PSCORES[1:2]), mode="threshold"), 0)
    assert f["n_proposals"] == 2
    assert f["prop_x_std"] == pytest.approx(0.5) and f["prop_l_std"] == 0
    assert [f[f"iou_bev_{s}"] for s in STATS] == pytest.approx([0.6, 0.6, 0.6, 0.0])


def test_zero_boxes():
    for mode, nf in (("exact", 90), ("threshold", 90), ("none", 17)):
        x = compute_features(POINTS, INTEN, np.zeros((0, 7)), [], [],
                             proposals=(PROPS, PSCORES), mode=mode, preimage=[])
        assert x.shape == (0, nf) and x.dtype == np.float64
    assert compute_features(POINTS, INTEN, [], [], [], mode="none",
                            class_scores=np.zeros((0, 3))).shape == (0, 20)


def test_boxes_at_the_cloud_edge():
    """Boxes beyond the last point, straddling it, or touching it with a face."""
    pts = np.array([[x, 0.0, 0.0] for x in np.arange(0.0, 10.5, 0.5)])  # cloud ends at 10
    inten = np.linspace(0, 1, len(pts))
    boxes = np.array([box(x=11.0), box(x=10.0), box(x=12.0), box(x=100.0, h=50)])
    x = compute_features(pts, inten, boxes, [0.5] * 4, [0] * 4, mode="none")
    # half outside: points 8.0 .. 10.0; face on the last point (inclusive); far away
    assert col(x, "points", "none").tolist() == [3, 5, 1, 0]
    assert col(x, "refl_max", "none")[0] == 1.0
    assert col(x, "refl_mean", "none")[1] == pytest.approx(inten[-5:].mean())
    assert np.isfinite(x).all()


def test_nan_points_are_ignored():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-3, 3, (300, 3))
    inten = rng.random(300)
    boxes = np.array([box(), box(x=1.5, yaw=0.4)])
    props = (np.array([box(x=0.3), box(x=1.2, yaw=0.3)]), [0.4, 0.6])
    ref = compute_features(pts, inten, boxes, [0.9, 0.8], [0, 1], proposals=props,
                           mode="threshold")
    bad = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, np.nan], [0.1, 0.1, 0.1]])
    x = compute_features(np.vstack([pts, bad]), np.r_[inten, 0.5, 0.5, 0.5, np.nan], boxes,
                         [0.9, 0.8], [0, 1], proposals=props, mode="threshold")
    np.testing.assert_array_equal(x, ref)


def test_invalid_boxes_and_proposals():
    boxes = np.array([box(), box(l=0.0), box(x=np.nan), box(x=1)])
    x = compute_features(POINTS, INTEN, boxes, [0.9, 0.9, 0.9, np.nan], [0] * 4,
                         proposals=(PROPS, PSCORES), mode="threshold")
    assert np.isfinite(x[0]).all() and np.isnan(x[1:]).all()
    # invalid proposals (NaN box, NaN score, zero size) belong to no set
    props = np.vstack([PROPS, [box(x=0.1, l=np.nan), box(x=0.1), box(x=0.1, h=0)]])
    y = compute_features(POINTS, INTEN, boxes[:1], [0.9], [0],
                         proposals=(props, np.r_[PSCORES, 0.5, np.nan, 0.5]),
                         mode="threshold")
    np.testing.assert_array_equal(y, x[:1])


def test_labels_class_names_and_extra_class_scores():
    b = np.array([box(), box(x=5), box(x=10)])
    kw = dict(class_names=["car", "pedestrian"], mode="none")
    x = compute_features(POINTS, INTEN, b, [0.5] * 3, ["pedestrian", "car", "tram"], **kw)
    assert col(x, "class", "none").tolist() == [1, 0, -1]
    assert col(compute_features(POINTS, INTEN, b, [.5] * 3, ["1", "0", "3"], mode="none"),
               "class", "none").tolist() == [1, 0, 3]
    with pytest.raises(ValueError):
        compute_features(POINTS, INTEN, b, [0.5] * 3, ["car"] * 3, mode="none")
    cs = np.array([[0.7, 0.2], [np.nan, 0.9], [0.1, 0.1]])
    y = compute_features(POINTS, INTEN, b, [0.5] * 3, [0, 1, 0], mode="threshold",
                         class_scores=cs)
    assert y.shape == (3, 92)
    np.testing.assert_array_equal(y[:, -2:], [[0.7, 0.2], [0, 0.9], [0.1, 0.1]])
    np.testing.assert_array_equal(y[:, :90], compute_features(
        POINTS, INTEN, b, [0.5] * 3, [0, 1, 0], mode="threshold"))


def test_class_aware_and_score_threshold():
    plab = np.array([2, 2, 1, 2, 2, 2])
    args = (POINTS, INTEN, np.array([box()]), [0.9], [2])
    def n(**kw):
        return col(compute_features(*args, proposals=(PROPS, PSCORES, plab),
                                    mode="threshold", **kw), "n_proposals")[0]
    assert n() == 3 and n(class_aware=True) == 2          # proposal 2 has another class
    assert n(proposal_score_threshold=0.6) == 2           # proposal 1 (0.5) drops out
    assert n(proposal_score_threshold=0.7) == 1           # "above": 0.7 is not above 0.7


def test_bad_arguments():
    b = np.array([box()])
    with pytest.raises(ValueError, match="preimage"):
        compute_features(POINTS, INTEN, b, [1], [0], proposals=(PROPS, PSCORES), mode="exact")
    with pytest.raises(ValueError):
        compute_features(POINTS, INTEN, b, [1], [0], proposals=(PROPS, PSCORES),
                         mode="exact", preimage=[[0, 99]])
    with pytest.raises(ValueError):
        compute_features(POINTS, INTEN, b, [1], [0], proposals=(PROPS, PSCORES),
                         mode="exact", preimage=[[0], [1]])
    with pytest.raises(ValueError):
        compute_features(POINTS, INTEN[:3], b, [1], [0], mode="none")
    with pytest.raises(ValueError):
        compute_features(POINTS, INTEN, b, [1], [0], mode="threshold", iou_threshold=1.0)
    with pytest.raises(ValueError):
        compute_features(POINTS, INTEN, b, [1], [0], mode="nms")


def test_heading_statistics_across_the_wrap():
    b = np.array([box(yaw=math.pi - 0.01)])
    props = np.array([box(yaw=math.pi - 0.05), box(yaw=-math.pi + 0.05)])
    f = row(compute_features(POINTS, INTEN, b, [0.9], [0], proposals=(props, [0.5, 0.5]),
                             mode="threshold"), 0)
    assert f["n_proposals"] == 3
    assert f["theta"] == pytest.approx(math.pi - 0.01)
    assert f["prop_theta_max"] == pytest.approx(math.pi + 0.05)
    assert f["prop_theta_std"] == pytest.approx(pstd([-0.01, -0.05, 0.05]))


def test_proposal_sets_from_nms():
    sup = np.array([0, 0, 3, 3, -1, 5, 3])
    s = ProposalSets.from_nms(sup, np.array([3, 0, 5]))
    assert s.offsets.tolist() == [0, 3, 5, 6]
    assert s.index.tolist() == [2, 3, 6, 0, 1, 5]
    d, p = s.pairs()
    assert d.tolist() == [0, 0, 0, 1, 1, 2] and p.tolist() == [2, 3, 6, 0, 1, 5]
    assert ProposalSets.from_lists([]).offsets.tolist() == [0]


# ---------------------------------------------------------------- random frames
def random_frame(seed, n_obj=6, n_prop=40):
    """Objects with surface-ish points, jittered detections and proposals around them."""
    rng = np.random.default_rng(seed)
    gt = np.column_stack([rng.uniform(-25, 25, (n_obj, 2)), rng.uniform(-1, 0, n_obj),
                          rng.uniform(1, 5, n_obj), rng.uniform(0.6, 2, n_obj),
                          rng.uniform(1, 2, n_obj), rng.uniform(-math.pi, math.pi, n_obj)])
    pts = [rng.uniform(-30, 30, (800, 3)) * [1, 1, 0.1]]
    for g in gt:
        loc = rng.uniform(-0.5, 0.5, (150, 3)) * g[3:6]
        c, s = math.cos(g[6]), math.sin(g[6])
        pts.append(np.column_stack([g[0] + c * loc[:, 0] - s * loc[:, 1],
                                    g[1] + s * loc[:, 0] + c * loc[:, 1], g[2] + loc[:, 2]]))
    pts = np.vstack(pts)

    def jitter(b, s):
        o = b.copy()
        o[:, :3] += rng.normal(size=(len(b), 3)) * s
        o[:, 3:6] *= np.exp(rng.normal(size=(len(b), 3)) * s / 2)
        o[:, 6] += rng.normal(size=len(b)) * s
        return o
    dets = jitter(gt, 0.1)
    props = np.vstack([dets[:3], jitter(gt[rng.integers(0, n_obj, n_prop)], 0.3)])
    out = (pts, rng.random(len(pts)), dets, rng.random(n_obj), rng.integers(0, 3, n_obj),
           props, rng.random(len(props)))
    # detections 0, 1 are among the proposals (their own scores); detection 2 has a
    # proposal of the same geometry but another score (another proposal, a member)
    out[6][:2] = out[3][:2]
    return out


@pytest.mark.parametrize("seed", range(4))
def test_matches_loop_reference(seed):
    pts, inten, dets, sc, lab, props, psc = random_frame(seed)
    for mode in ("none", "threshold"):
        x = compute_features(pts, inten, dets, sc, lab, proposals=(props, psc), mode=mode)
        ref = ref_features(pts, inten, dets, sc, lab, props, psc, mode)
        np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9, err_msg=mode)
    nms = rotated_nms(props, psc, 0.3, max_output=4)
    sets = ProposalSets.from_nms(nms.suppressed_by, nms.keep)
    lists = [sets.index[sets.offsets[k]:sets.offsets[k + 1]] for k in range(len(nms.keep))]
    assert sum(map(len, lists)) > len(lists)  # some real pre-images
    x = compute_features(pts, inten, props[nms.keep], psc[nms.keep], lab[:len(nms.keep)],
                         proposals=(props, psc), mode="exact", preimage=sets)
    ref = ref_features(pts, inten, props[nms.keep], psc[nms.keep], lab[:len(nms.keep)],
                       props, psc, "exact", sets=lists)
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9)


def _transform(b, rot, t):
    c, s = math.cos(rot), math.sin(rot)
    o = b.copy()
    o[:, 0], o[:, 1] = c * b[:, 0] - s * b[:, 1] + t[0], s * b[:, 0] + c * b[:, 1] + t[1]
    o[:, 2] = b[:, 2] + t[2]
    if o.shape[1] == 7:
        o[:, 6] = b[:, 6] + rot
    return o


@pytest.mark.parametrize("seed", range(3))
def test_rigid_motion_invariance(seed):
    """Rotate about z and translate the whole frame: position-free features are equal;
    z features shift by t_z; headings relative to the box's own are equal."""
    pts, inten, dets, sc, lab, props, psc = random_frame(seed + 10)
    rng = np.random.default_rng(seed)
    rot, t = rng.uniform(-math.pi, math.pi), rng.uniform(-50, 50, 3)
    for mode in ("threshold", "exact"):
        pre = None
        if mode == "exact":
            nms = rotated_nms(props, psc, 0.3)
            pre, dets_m, sc_m = (ProposalSets.from_nms(nms.suppressed_by, nms.keep),
                                 props[nms.keep], psc[nms.keep])
            lab_m = np.zeros(len(nms.keep), int)
        else:
            dets_m, sc_m, lab_m = dets, sc, lab
        def run(p, d, pr):
            return compute_features(p, inten, d, sc_m, lab_m, proposals=(pr, psc),
                                    mode=mode, preimage=pre)
        a = run(pts, dets_m, props)
        b = run(_transform(pts, rot, t), _transform(dets_m, rot, t), _transform(props, rot, t))
        names = feature_names(mode)
        moving = {"x", "y", "z", "theta"} | {f"prop_{q}_{s}" for q in "xy" for s in STATS} \
            | {f"prop_{q}_{s}" for q in ("z", "theta") for s in STATS[:3]}
        fixed = [k for k, nm in enumerate(names) if nm not in moving]
        assert len(fixed) == 90 - 4 - 8 - 6
        assert np.ptp(a[:, names.index("points")]) > 0  # a non-trivial frame
        np.testing.assert_allclose(b[:, fixed], a[:, fixed], rtol=1e-9, atol=1e-9)
        for nm in ("z", "prop_z_min", "prop_z_max", "prop_z_mean"):
            k = names.index(nm)
            np.testing.assert_allclose(b[:, k], a[:, k] + t[2], atol=1e-9)
        th = names.index("theta")
        for nm in ("prop_theta_min", "prop_theta_max", "prop_theta_mean"):
            k = names.index(nm)
            np.testing.assert_allclose(b[:, k] - b[:, th], a[:, k] - a[:, th], atol=1e-9)
        d_th = (b[:, th] - a[:, th] - rot + math.pi) % (2 * math.pi) - math.pi
        np.testing.assert_allclose(d_th, 0, atol=1e-9)


# ---------------------------------------------------------------- compiled set statistics
@pytest.mark.parametrize("n", [0, 1, 2, 7, 8, 9, 15, 16, 17, 127, 128, 129, 300, 1031])
def test_pairwise_sum_has_numpys_bits(n):
    from lidar_quality_core.lmd.features import _pairwise_sum

    rng = np.random.default_rng(n)
    a = rng.normal(size=n + 3) * 10.0 ** rng.uniform(-8, 8, size=n + 3)
    got = np.float64(_pairwise_sum(a, 3, n))
    want = np.add.reduce(a[3:])  # numpy's own pairwise reduction of the same values
    assert got.view(np.uint64) == want.view(np.uint64) or (n == 0 and got == want)


def test_pairwise_sum_keeps_negative_zero():
    from lidar_quality_core.lmd.features import _pairwise_sum

    assert math.copysign(1.0, _pairwise_sum(np.full(4, -0.0), 0, 4)) == -1.0


def _set_columns_numpy(q, cls, d, prow, theta, v_bev, v_3d, t, all_3d):
    """The numpy chain the compiled kernel replaced (sets: own row, then members)."""
    n = len(cls)
    own = np.insert(q[:n], OWN_QUANTITIES.index("class"), cls, axis=1)
    counts = 1 + np.bincount(d, minlength=n)
    seg = np.concatenate([np.arange(n), d])
    order = np.argsort(seg, kind="stable")
    rows = np.concatenate([q[:n], q[n:][prow]])
    rows[:n, 6] = q[:n, 6] + 0.0
    rows[n:, 6] = theta
    rows = rows[order]
    starts = np.zeros(n, np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    cnt = counts[:, None].astype(float)
    mean = np.add.reduceat(rows, starts, axis=0) / cnt
    dev = rows - np.repeat(mean, counts, axis=0)
    dev *= dev
    std = np.sqrt(np.add.reduceat(dev, starts, axis=0) / cnt)
    st = np.stack([np.minimum.reduceat(rows, starts, axis=0),
                   np.maximum.reduceat(rows, starts, axis=0), mean, std], axis=2)
    parts = [own, st.reshape(n, -1)]
    sel = np.ones(len(d), bool) if all_3d else v_3d > t
    for v, b in ((v_3d[sel], d[sel]), (v_bev, d)):
        s = np.zeros((n, 4))
        for k in range(n):
            x = v[b == k]
            if len(x):
                s[k] = x.min(), x.max(), x.mean(), np.sqrt(((x - x.mean()) ** 2).mean())
        parts.append(s)
    return np.concatenate(parts + [cnt], axis=1)


@pytest.mark.parametrize("seed", range(6))
def test_set_columns_match_the_numpy_chain(seed):
    from lidar_quality_core.lmd.features import _set_columns

    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(1, 40)), int(rng.integers(0, 300))
    q = rng.normal(size=(n + m, 16)) * 10.0 ** rng.uniform(-3, 3, size=16)
    q[rng.random(q.shape) < 0.01] = -0.0
    d = np.sort(rng.integers(0, n, size=3 * m if m else 0))
    if seed == 5 and m:
        d[:] = 0                       # one set of > 128 members: numpy halves its sum
    prow = rng.integers(0, max(m, 1), size=len(d)) if m else np.zeros(0, np.int64)
    theta = rng.uniform(-4, 4, size=len(d))
    v_bev, v_3d = rng.random(len(d)), rng.random(len(d)) * 0.8
    cls = rng.integers(0, 4, size=n).astype(float)
    for all_3d in (False, True):
        want = _set_columns_numpy(q, cls, d, prow, theta, v_bev, v_3d, 0.5, all_3d)
        got = np.empty((n, 90))
        got[:, :17] = want[:, :17]  # the own quantities: compute_features' (tests above)
        _set_columns(q, d, prow, theta, v_bev, v_3d, 0.5, all_3d, got)
        # set statistics and counts to the bit; the IoU statistics as _pair_stats sums them
        assert np.array_equal(got[:, :81].view(np.uint64), want[:, :81].view(np.uint64))
        assert np.array_equal(got[:, 89], want[:, 89])
        np.testing.assert_allclose(got[:, 81:89], want[:, 81:89], rtol=1e-12, atol=1e-15)


def _odd_boxes(rng, n):
    """Boxes with the values that take other branches: NaN, inf, sizes 0 and < 0."""
    b = rng.normal(size=(n, 7)) * [10, 10, 1, 2, 1, 1, 3] + [0, 0, 0, 4, 2, 1.5, 0]
    b[rng.random(b.shape) < 0.03] = np.nan
    b[rng.random(b.shape) < 0.02] = np.inf
    b[rng.random(n) < 0.05, 3] = 0.0
    b[rng.random(n) < 0.05, 5] = -1.0
    return b


@pytest.mark.parametrize("seed", range(4))
def test_compiled_box_helpers_match_numpy(seed):
    from lidar_quality_core.box_geometry import SegmentStats
    from lidar_quality_core.conventions import wrap_angle
    from lidar_quality_core.lmd.features import _box_ok, _derived_iou_3d, _quantities

    rng = np.random.default_rng(seed)
    b, pb = _odd_boxes(rng, 60), _odd_boxes(rng, 200)
    sc = rng.random(60)
    sc[::11] = np.nan
    with np.errstate(invalid="ignore"):
        want_ok = (np.isfinite(b).all(axis=1) & np.isfinite(sc)
                   & (np.min(b[:, 3:6], axis=1, initial=np.inf) > 0.0))
    assert np.array_equal(_box_ok(b, sc), want_ok)

    cnt = rng.integers(0, 50, 60)
    st = SegmentStats(cnt, rng.random(60), rng.random(60), rng.random(60), rng.random(60))
    for n_points in (0, 1234):
        q = _quantities(b, sc, st, n_points)
        l, w, h = b[:, 3], b[:, 4], b[:, 5]
        with np.errstate(all="ignore"):
            vol, surf = l * w * h, 2.0 * (l * w + l * h + w * h)
            want = np.column_stack([b[:, :6], wrap_angle(b[:, 6]), sc, vol, surf, vol / surf,
                                    cnt, cnt / n_points if n_points else np.zeros(60),
                                    st.max, st.mean, st.std])
        assert np.array_equal(q, want, equal_nan=True)

    d, p = rng.integers(0, 60, 500), rng.integers(0, 200, 500)
    v = rng.random(500)
    v[::50] = 0.0
    a, c = b[d], pb[p]
    with np.errstate(all="ignore"):  # the numpy chain the kernel replaced
        aa, ab = a[:, 3] * a[:, 4], c[:, 3] * c[:, 4]
        inter = v * (aa + ab) / (1.0 + v)
        top = np.minimum(a[:, 2] + a[:, 5] / 2, c[:, 2] + c[:, 5] / 2)
        bot = np.maximum(a[:, 2] - a[:, 5] / 2, c[:, 2] - c[:, 5] / 2)
        inter *= np.maximum(top - bot, 0.0)
        union = aa * a[:, 5] + ab * c[:, 5] - inter
        want = np.clip(np.nan_to_num(np.where(union > 0, inter / union, 0.0), nan=0.0), 0, 1)
    assert np.array_equal(_derived_iou_3d(b, pb, d, p, v), want)


def _canonical_numpy(sc, d, p, v_bev, v_3d, pb, ps):
    """The numpy chain _without_self_copies replaced (lexsorts), and np.unique."""
    from lidar_quality_core.lmd.features import SELF_IOU, SELF_SCORE_TOL

    order = np.lexsort((ps[p], d))
    d, p, v_bev, v_3d = d[order], p[order], v_bev[order], v_3d[order]
    ms = ps[p]
    if np.any((d[1:] == d[:-1]) & (ms[1:] == ms[:-1])):
        order = np.lexsort(tuple(pb[p][:, ::-1].T) + (ms, d))
        d, p, v_bev, v_3d, ms = d[order], p[order], v_bev[order], v_3d[order], ms[order]
    gap = np.abs(ms - sc[d])
    cand = np.flatnonzero((v_3d >= SELF_IOU)
                          & (gap <= SELF_SCORE_TOL * np.maximum(1.0, np.abs(sc[d]))))
    if len(cand):
        cand = cand[np.lexsort((-v_3d[cand], gap[cand], d[cand]))]
        other = np.ones(len(d), dtype=bool)
        other[cand[np.unique(d[cand], return_index=True)[1]]] = False
        d, p, v_bev, v_3d = d[other], p[other], v_bev[other], v_3d[other]
    return (d, p, v_bev, v_3d) + np.unique(p, return_inverse=True)


@pytest.mark.parametrize("seed", range(8))
def test_canonical_sets_match_the_lexsorts(seed):
    from lidar_quality_core.lmd.features import _without_self_copies

    rng = np.random.default_rng(seed)
    n, m, k = 12, 80, int(rng.integers(0, 400))
    sc = rng.random(n)
    pb = rng.normal(size=(m, 7))
    ps = np.round(rng.random(m), 1 if seed % 2 else 6)   # odd seeds: many equal scores
    pb[1::9] = pb[0]                                      # equal boxes, equal scores too
    ps[1::9] = ps[0]
    d = rng.integers(0, n, k) if seed % 3 else np.sort(rng.integers(0, n, k))
    p = rng.integers(0, m, k)
    v_bev = rng.random(k)
    v_3d = np.where(rng.random(k) < 0.3, 1.0, v_bev * 0.9)
    copies = rng.random(k) < 0.3                          # members that are the box itself
    ps_copy = ps.copy()
    p[copies] = m - 1 - np.arange(copies.sum()) % 5
    ps_copy[m - 5:] = sc[d[copies][:5]] if copies.sum() >= 5 else ps_copy[m - 5:]
    want = _canonical_numpy(sc, d, p, v_bev, v_3d, pb, ps_copy)
    got = _without_self_copies(sc, d, p, v_bev, v_3d, pb, ps_copy)
    for g, w in zip(got, want):
        assert np.array_equal(g, w)
