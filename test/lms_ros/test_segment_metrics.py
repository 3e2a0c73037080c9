"""LidarMetaSeg metrics: hand-built range images with known values, and a brute-force
implementation of the paper's definitions (pixel sets, breadth-first search) that the
vectorized module must reproduce exactly on random clouds."""
import math
from collections import deque

import numpy as np
import pytest

from lidar_quality_core.range_image import RangeImageConfig, project
from lms_ros.segment_metrics import (MEASURES, compute_segments, label_periodic,
                                     metric_names, n_metrics, segment_targets, to_points)

NB8 = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]


def pixel_points(cfg, rows, cols, rng_m=10.0):
    """Points at the centres of pixels (rows, cols) of a uniform config."""
    R, C = cfg.shape
    up, down = cfg.fov_up_deg, cfg.fov_down_deg
    rows, cols = np.asarray(rows, float), np.asarray(cols, float)
    el = np.radians(up - (rows + 0.5) * (up - down) / R)
    az = np.pi * (1.0 - 2.0 * (cols + 0.5) / C)
    r = np.broadcast_to(np.asarray(rng_m, float), rows.shape)
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                     r * np.sin(el)], axis=1)


def image_cloud(cfg, classes, rng_m=10.0, sharp=0.9):
    """One point per pixel of ``classes`` (rows, cols; -1 = no point), probability
    ``sharp`` on its class and the rest spread evenly; returns xyz, probs, n."""
    rows, cols = np.nonzero(classes >= 0)
    cls = classes[rows, cols]
    n = int(classes.max()) + 1
    xyz = pixel_points(cfg, rows, cols, rng_m)
    probs = np.full((len(cls), n), (1 - sharp) / max(n - 1, 1))
    probs[np.arange(len(cls)), cls] = sharp if n > 1 else 1.0
    return xyz, probs, n


# -- brute force -------------------------------------------------------------------------


def brute_fill(mask):
    R, C = mask.shape
    qr, qc = np.nonzero(mask)
    out = np.empty((R, C), dtype=np.int64)
    for r in range(R):
        for c in range(C):
            d_right, d_left = (qc - c) % C, (c - qc) % C
            dc = np.minimum(d_left, d_right)
            d2 = dc * dc + (qr - r) ** 2
            best = min(zip(d2, np.abs(qr - r), (d_left > d_right).astype(int), qr, qc))
            out[r, c] = best[3] * C + best[4]
    return out


def neighbours(r, c, R, C):
    return {(r + dr, (c + dc) % C) for dr, dc in NB8 if 0 <= r + dr < R}


def components(img):
    R, C = img.shape
    seen, comps = set(), []
    for r in range(R):
        for c in range(C):
            if (r, c) in seen or img[r, c] < 0:
                continue
            comp, todo = {(r, c)}, deque([(r, c)])
            seen.add((r, c))
            while todo:
                p = todo.popleft()
                for q in neighbours(*p, R, C):
                    if q not in seen and img[q] == img[r, c]:
                        seen.add(q)
                        comp.add(q)
                        todo.append(q)
            comps.append(comp)
    return comps


def brute(xyz, probs, cfg, ring=None, intensity=None, min_points=10):
    """The paper's definitions, literally, per segment: {frozenset(pixels): features}."""
    proj = project(xyz, cfg, ring)
    R, C = cfg.shape
    mask = proj.index >= 0
    src = proj.index.reshape(-1)[brute_fill(mask).reshape(-1)].reshape(R, C)
    n = probs.shape[1]
    inten = np.zeros(len(xyz)) if intensity is None else intensity
    heat = {m: np.zeros((R, C)) for m in MEASURES}
    Y = np.zeros((R, C), int)
    for r in range(R):
        for c in range(C):
            j = src[r, c]
            p = [float(v) for v in probs[j]]
            top = sorted(p, reverse=True)
            Y[r, c] = int(np.argmax(probs[j]))
            heat["E"][r, c] = (-sum(v * math.log(v) for v in p if v > 0) / math.log(n)
                               if n > 1 else 0.0)
            heat["V"][r, c] = 1 - top[0]
            heat["D"][r, c] = 1 - top[0] + (top[1] if n > 1 else 0.0)
            x, y, z = (float(v) for v in xyz[j])
            heat["x"][r, c], heat["y"][r, c], heat["z"][r, c] = x, y, z
            heat["i"][r, c] = inten[j]
            heat["r"][r, c] = math.sqrt(x * x + y * y + z * z)
    out = {}
    for k in components(Y):
        inner = {p for p in k if all(0 <= p[0] + dr < R for dr in (-1, 1))
                 and neighbours(*p, R, C) <= k}
        bd = k - inner
        S, S_in, S_bd = len(k), len(inner), len(bd)
        SP = sum(bool(mask[p]) for p in k)
        if SP < min_points:
            continue
        row = []
        for m in MEASURES:
            mu, va = {}, {}
            for name, reg in (("", k), ("_in", inner), ("_bd", bd)):
                vals = np.array([heat[m][p] for p in reg])
                mu[name] = vals.mean() if len(vals) else 0.0
                va[name] = (vals ** 2).mean() - vals.mean() ** 2 if len(vals) else 0.0
            row += [mu[""], mu["_in"], mu["_bd"], mu[""] * S / S_bd, mu["_in"] * S_in / S_bd,
                    va[""], va["_in"], va["_bd"], va[""] * S / S_bd, va["_in"] * S_in / S_bd]
        row += [S, S_in, S_bd, S / S_bd, S_in / S_bd, SP]
        knb = set().union(*(neighbours(*p, R, C) for p in k)) - k
        row += [sum(Y[p] == c for p in knb) / len(knb) if knb else 0.0 for c in range(n)]
        row += [np.mean([probs[src[p], c] for p in k]) for c in range(n)]
        out[frozenset(k)] = np.array(row, dtype=float)
    return out, src, Y, mask


def brute_targets(res, gt, ignore_label=None):
    R, C = res.segments.shape
    n = res.n_classes
    src = res.source
    G = np.asarray(gt)[src]
    d = res.delta & (G != (-99 if ignore_label is None else ignore_label))
    pred = components(res.pred)
    gts = components(np.where(G == (-99 if ignore_label is None else ignore_label), n, G))
    out = {}
    for k in pred:
        c = res.pred[next(iter(k))]
        Kp = set().union(*[g for g in gts if G[next(iter(g))] == c and g & k] or [set()])
        Q = set().union(*[q for q in pred if res.pred[next(iter(q))] == c and q & Kp]
                        or [set()])

        def size(s):
            return sum(bool(d[p]) for p in s)

        inter = size(k & Kp)
        u, ua = size(k | Kp), size(k | (Kp - Q))
        out[frozenset(k)] = (inter / u if u else np.nan, inter / ua if ua else np.nan)
    return out


def pixel_sets(res):
    seg = res.segments
    return {s: frozenset(zip(*np.nonzero(seg == s))) for s in range(res.n_segments)}


def random_scene(seed, R=6, C=12, n=4):
    rng = np.random.default_rng(seed)
    cfg = RangeImageConfig.uniform(R, C, 10.0, -20.0)
    # blocky class image so that segments are bigger than a pixel
    base = rng.integers(0, n, (R // 2 + 1, C // 3 + 1))
    cls_img = np.kron(base, np.ones((2, 3), int))[:R, :C]
    flip = rng.random((R, C)) < 0.15
    cls_img[flip] = rng.integers(0, n, flip.sum())
    occupied = rng.random((R, C)) < 0.75
    rows, cols = np.nonzero(occupied)
    extra = rng.random(len(rows)) < 0.2            # a second point in some pixels
    rows = np.r_[rows, rows[extra]]
    cols = np.r_[cols, cols[extra]]
    xyz = pixel_points(cfg, rows + rng.uniform(-0.3, 0.3, len(rows)),
                       cols + rng.uniform(-0.3, 0.3, len(rows)),
                       rng.uniform(2.0, 50.0, len(rows)))
    logits = rng.normal(0, 1, (len(rows), n))
    logits[np.arange(len(rows)), cls_img[rows, cols]] += 2.5
    # the second points are often of another class (shadowed by the nearer one)
    k = int(extra.sum())
    if k:
        logits[-k:] = rng.normal(0, 3, (k, n))
    probs = np.exp(logits)
    probs /= probs.sum(axis=1, keepdims=True)
    # out of the field of view, NaN: never projected
    xyz = np.r_[xyz, pixel_points(cfg, [-3.0, R + 2.0], [1.0, 2.0]), [[np.nan, 0, 0]]]
    probs = np.r_[probs, np.full((3, n), 1.0 / n)]
    inten = rng.uniform(0, 1, len(xyz))
    gt = np.r_[cls_img[rows, cols], [0, 0, 0]]
    swap = rng.random(len(gt)) < 0.1
    gt[swap] = rng.integers(0, n, swap.sum())
    return cfg, xyz, probs.astype(np.float32), inten, gt


# -- schema ------------------------------------------------------------------------------


def test_schema_count_and_names():
    for n in (1, 13, 19, 20):
        names = metric_names(n)
        assert len(names) == n_metrics(n) == 86 + 2 * n
        assert len(set(names)) == len(names)
    names = metric_names(2, ["road", "car"])
    assert names[:10] == ("mean_E", "mean_E_in", "mean_E_bd", "mean_E_rel", "mean_E_rel_in",
                          "var_E", "var_E_in", "var_E_bd", "var_E_rel", "var_E_rel_in")
    assert names[70:80] == tuple(s.replace("E", "r") for s in names[:10])
    assert names[80:86] == ("S", "S_in", "S_bd", "S_rel", "S_rel_in", "SP")
    assert names[86:] == ("N_road", "N_car", "P_road", "P_car")
    assert metric_names(2)[86:] == ("N_0", "N_1", "P_0", "P_1")
    with pytest.raises(ValueError):
        metric_names(2, ["a"])
    with pytest.raises(ValueError):
        metric_names(2, ["a", "a"])


# -- hand-built images -------------------------------------------------------------------


def test_hand_built_image_known_values():
    # 6 x 10 image, one point per pixel. Class 1: a 4 x 4 block (rows 1-4, cols 3-6),
    # class 0 everywhere else (one segment around it, across the seam)
    cfg = RangeImageConfig.uniform(6, 10, 10.0, -20.0)
    img = np.zeros((6, 10), int)
    img[1:5, 3:7] = 1
    xyz, probs, n = image_cloud(cfg, img, rng_m=10.0, sharp=0.8)
    inten = np.arange(len(xyz), dtype=float)
    res = compute_segments(xyz, probs, cfg, intensity=inten, min_points=1)
    assert res.n_segments == 2
    f = dict(zip(res.names, res.features[res.segment_class[res.kept_ids] == 1][0]))
    # the block: S 16, interior its 2 x 2 centre, boundary 12
    assert (f["S"], f["S_in"], f["S_bd"], f["SP"]) == (16, 4, 12, 16)
    assert f["S_rel"] == pytest.approx(16 / 12) and f["S_rel_in"] == pytest.approx(4 / 12)
    # probabilities (0.2, 0.8) everywhere: E, D, V constant, variances 0
    E = -(0.2 * math.log(0.2) + 0.8 * math.log(0.8)) / math.log(2)
    for name, v in (("E", E), ("D", 1 - 0.8 + 0.2), ("V", 0.2)):
        for reg in ("", "_in", "_bd"):
            assert f[f"mean_{name}{reg}"] == pytest.approx(v, abs=1e-6)
            assert f[f"var_{name}{reg}"] == pytest.approx(0.0, abs=1e-9)
        assert f[f"mean_{name}_rel"] == pytest.approx(v * 16 / 12, abs=1e-6)
        assert f[f"mean_{name}_rel_in"] == pytest.approx(v * 4 / 12, abs=1e-6)
    assert f["mean_r"] == pytest.approx(10.0, abs=1e-5)
    assert f["var_r"] == pytest.approx(0.0, abs=1e-9)
    # neighbourhood: the 6 x 6 ring around the block, all class 0
    assert (f["N_0"], f["N_1"]) == (1.0, 0.0)
    assert (f["P_0"], f["P_1"]) == (pytest.approx(0.2), pytest.approx(0.8))
    # intensity = point index: mean over the block's points, variance of those values
    vals = inten[(img[img >= 0] == 1)]
    assert f["mean_i"] == pytest.approx(vals.mean())
    assert f["var_i"] == pytest.approx(vals.var())
    # the surrounding class-0 segment: everything else; rows 0 and 5 are its boundary
    g = dict(zip(res.names, res.features[res.segment_class[res.kept_ids] == 0][0]))
    assert g["S"] == 60 - 16
    inner = np.zeros((6, 10), bool)
    inner[1:5] = True
    inner[0:6, 2:8] = False          # pixels next to the block are boundary
    inner[[0, 5]] = False
    assert g["S_in"] == inner.sum() == 16
    assert g["N_1"] == 1.0


def test_heatmap_definitions_on_one_pixel_segments():
    cfg = RangeImageConfig.uniform(3, 4, 10.0, -20.0)
    p = np.array([0.5, 0.3, 0.2, 0.0], np.float32)          # a zero: 0 log 0 = 0
    xyz = pixel_points(cfg, np.repeat(np.arange(3), 4), np.tile(np.arange(4), 3))
    probs = np.tile(p, (12, 1))
    res = compute_segments(xyz, probs, cfg, min_points=1)
    assert res.n_segments == 1
    E = -(0.5 * math.log(0.5) + 0.3 * math.log(0.3) + 0.2 * math.log(0.2)) / math.log(4)
    np.testing.assert_allclose(res.point_E, E, rtol=1e-6)
    np.testing.assert_allclose(res.point_D, 1 - 0.5 + 0.3, rtol=1e-6)
    np.testing.assert_allclose(res.point_V, 0.5, rtol=1e-6)
    # ties: argmax takes the lowest class, the second largest equals the largest
    probs = np.tile(np.array([0.2, 0.4, 0.4, 0.0], np.float32), (12, 1))
    res = compute_segments(xyz, probs, cfg, min_points=1)
    assert (res.point_class == 1).all()
    np.testing.assert_allclose(res.point_D, 1.0, rtol=1e-6)


def test_single_class_is_one_segment_without_neighbours():
    cfg = RangeImageConfig.uniform(5, 8, 10.0, -20.0)
    img = np.zeros((5, 8), int)
    img[2, 3] = -1                                         # one empty pixel, filled
    xyz, _, _ = image_cloud(cfg, img)
    probs = np.ones((len(xyz), 1), np.float32)             # one class
    res = compute_segments(xyz, probs, cfg)
    assert res.n_segments == 1 and len(res.kept_ids) == 1
    f = dict(zip(res.names, res.features[0]))
    assert (f["S"], f["SP"], f["S_in"], f["S_bd"]) == (40, 39, 24, 16)  # rows 0, 4 boundary
    assert f["N_0"] == 0.0 and f["P_0"] == 1.0
    assert f["mean_E"] == 0.0 and f["mean_V"] == 0.0 and f["mean_D"] == 0.0
    assert len(res.names) == 88
    assert (res.point_segment == 0).all()


def test_seam_joins_segments_and_neighbourhoods():
    cfg = RangeImageConfig.uniform(5, 12, 10.0, -20.0)
    img = np.zeros((5, 12), int)
    img[1:4, [0, 1, 11]] = 1          # a block across the seam
    img[0, 10] = 2                    # touches it only diagonally across nothing: apart
    img[4, 2] = 1                     # diagonal neighbour of (3, 1): same segment
    img[2, 6] = 1                     # far away: another segment
    img[4, 10] = 1                    # diagonal to (3, 11): same segment
    xyz, probs, n = image_cloud(cfg, img)
    res = compute_segments(xyz, probs, cfg, min_points=1)
    seg = res.segments
    block = seg[2, 0]
    for p in [(1, 11), (3, 1), (4, 2), (4, 10), (2, 11)]:
        assert seg[p] == block
    assert seg[2, 6] != block
    assert (res.segment_class == 1).sum() == 2
    # a seam-crossing diagonal: (0, 11) and (1, 0) of class 3 in another image
    img2 = np.zeros((4, 6), int)
    img2[0, 5] = img2[1, 0] = 3
    img2[2, 2] = 1
    xyz2, probs2, _ = image_cloud(RangeImageConfig.uniform(4, 6, 10.0, -20.0), img2)
    r2 = compute_segments(xyz2, probs2, RangeImageConfig.uniform(4, 6, 10.0, -20.0),
                          min_points=1)
    assert r2.segments[0, 5] == r2.segments[1, 0]
    # interior across the seam: column 0 sees column 11
    big = np.zeros((5, 12), int)
    big[:, [10, 11, 0, 1]] = 1
    xyz3, probs3, _ = image_cloud(cfg, big)
    r3 = compute_segments(xyz3, probs3, cfg, min_points=1)
    assert r3.interior[2, 11] and r3.interior[2, 0]
    assert not r3.interior[2, 1] and not r3.interior[0, 0]


def test_neighbourhood_counts_each_pixel_once():
    # a U-shaped class-1 segment around a class-0 pixel: that pixel borders the segment
    # in 7 directions but is one neighbourhood pixel
    cfg = RangeImageConfig.uniform(5, 9, 10.0, -20.0)
    img = np.full((5, 9), 2)
    img[1:4, 3:6] = 1
    img[2, 4] = 0
    xyz, probs, n = image_cloud(cfg, img)
    res = compute_segments(xyz, probs, cfg, min_points=1)
    f = dict(zip(res.names, res.features[res.segment_class[res.kept_ids] == 1][0]))
    # neighbourhood: the 5 x 5 ring minus the block (16 pixels of class 2) + the hole
    assert f["N_0"] == pytest.approx(1 / 17)
    assert f["N_2"] == pytest.approx(16 / 17)
    hole = dict(zip(res.names, res.features[res.segment_class[res.kept_ids] == 0][0]))
    assert hole["N_1"] == 1.0 and hole["S"] == 1 and hole["S_in"] == 0
    assert hole["mean_E_in"] == 0.0 and hole["var_E_in"] == 0.0 and hole["S_rel_in"] == 0.0


# -- against the brute force -------------------------------------------------------------


@pytest.mark.parametrize("seed", range(40))
def test_matches_brute_force(seed):
    cfg, xyz, probs, inten, gt = random_scene(seed, R=3 + seed % 5, C=5 + seed % 11,
                                              n=1 + seed % 5)
    if seed % 4 == 1:                       # exact zeros: 0 log 0 = 0
        probs[np.random.default_rng(seed).random(probs.shape) < 0.3] = 0.0
    min_points = seed % 4
    res = compute_segments(xyz, probs, cfg, intensity=inten, min_points=min_points)
    want, src, Y, mask = brute(xyz, probs, cfg, intensity=inten, min_points=min_points)
    np.testing.assert_array_equal(res.source, src)
    np.testing.assert_array_equal(res.pred, Y)
    sets = pixel_sets(res)
    assert sorted(map(len, sets.values())) == sorted(map(len, components(Y)))
    got = {sets[s]: row for s, row in zip(res.kept_ids, res.features)}
    assert set(got) == set(want)
    for k, row in want.items():
        np.testing.assert_allclose(got[k], row, rtol=2e-5, atol=1e-6,
                                   err_msg=str(sorted(k)))
    # targets
    iou, adj = segment_targets(res, gt, kept_only=False)
    bt = brute_targets(res, gt)
    for s, k in sets.items():
        np.testing.assert_allclose([iou[s], adj[s]], bt[k], err_msg=str(sorted(k)))
    iou_k, adj_k = segment_targets(res, gt)
    np.testing.assert_array_equal(iou_k, iou[res.kept_ids])
    # every projected point that keeps its pixel is in that pixel's segment
    p = res.projection
    w = p.winner
    np.testing.assert_array_equal(res.point_segment[w], res.segments.reshape(-1)[p.pixel[w]])
    assert (res.point_segment[~p.valid] == -1).all()
    np.testing.assert_array_equal(res.n_points,
                                  np.bincount(res.point_segment[res.point_segment >= 0],
                                              minlength=res.n_segments))


def test_shadowed_points_join_a_neighbouring_segment_of_their_class():
    cfg = RangeImageConfig.uniform(4, 8, 10.0, -20.0)
    img = np.zeros((4, 8), int)
    img[1:3, 4:6] = 1
    xyz, probs, n = image_cloud(cfg, img, rng_m=10.0)
    # behind pixel (1, 3) (class 0), a farther point predicted class 1: its pixel's
    # segment is class 0, its left / right neighbours: (1, 2) class 0, (1, 4) class 1
    far = pixel_points(cfg, [1], [3], 30.0)
    # behind (0, 0): a class-2 point without any class-2 pixel around
    far2 = pixel_points(cfg, [0], [0], 30.0)
    xyz = np.r_[xyz, far, far2]
    probs = np.r_[np.c_[probs, np.zeros(len(probs))], [[0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]]
    res = compute_segments(xyz, probs.astype(np.float32), cfg, min_points=1)
    assert res.point_segment[-2] == res.segments[1, 4]
    assert res.point_segment[-1] == -1
    assert res.n_points[res.segments[1, 4]] == 5


# -- targets -----------------------------------------------------------------------------


def test_iou_adj_one_ground_truth_segment_two_predicted_segments():
    # ground truth: class 1 on row 2, cols 1..10 (10 pixels). Prediction: class 1 on
    # cols 1..4 and 6..10, class 0 at col 5 (splits the ground-truth segment in two)
    cfg = RangeImageConfig.uniform(5, 14, 10.0, -20.0)
    pred = np.zeros((5, 14), int)
    pred[2, 1:5] = 1
    pred[2, 6:11] = 1
    gt_img = np.zeros((5, 14), int)
    gt_img[2, 1:11] = 1
    xyz, probs, n = image_cloud(cfg, pred)
    gt = gt_img[pred >= 0]
    res = compute_segments(xyz, probs, cfg, min_points=1)
    iou, adj = segment_targets(res, gt)
    a, b = res.segments[2, 1], res.segments[2, 6]
    ka, kb = (np.flatnonzero(res.kept_ids == s)[0] for s in (a, b))
    assert iou[ka] == pytest.approx(4 / 10) and iou[kb] == pytest.approx(5 / 10)
    # IoU_adj: the other predicted segment's pixels do not count; col 5 (missed) does
    assert adj[ka] == pytest.approx(4 / 5) and adj[kb] == pytest.approx(5 / 6)
    # the class-0 segment: GT class 0 everywhere except row 2 cols 1..10; it contains
    # (2, 5) predicted 0 whose GT is 1
    c0 = np.flatnonzero(res.segment_class[res.kept_ids] == 0)
    assert len(c0) == 1
    n0 = (pred == 0).sum()
    assert iou[c0[0]] == pytest.approx((n0 - 1) / (n0 + 0)) and adj[c0[0]] == iou[c0[0]]
    # a false positive: predicted class 1 where the ground truth has none
    gt2 = np.zeros_like(gt)
    iou2, adj2 = segment_targets(res, gt2)
    assert iou2[ka] == 0.0 and adj2[ka] == 0.0


def test_targets_count_projected_pixels_only_and_ignore_label():
    cfg = RangeImageConfig.uniform(3, 8, 10.0, -20.0)
    pred = np.zeros((3, 8), int)
    pred[1, 2:6] = 1
    pred[1, 3] = -1                    # an empty pixel inside the segment: filled, not counted
    xyz, probs, n = image_cloud(cfg, pred)
    gt = np.ones(len(xyz), int)        # GT: class 1 everywhere
    res = compute_segments(xyz, probs, cfg, min_points=1)
    assert res.size[res.segments[1, 2]] == 4 and res.size_projected[res.segments[1, 2]] == 3
    iou, adj = segment_targets(res, gt, kept_only=False)
    s = res.segments[1, 2]
    assert iou[s] == pytest.approx(3 / 23)       # 23 projected pixels of GT class 1
    assert adj[s] == pytest.approx(3 / 23)       # the rest is predicted 0: no other seg of 1
    # GT ignored on 20 of the points: they count nowhere
    gt_ign = gt.copy()
    gt_ign[pred[pred >= 0] == 0] = 255
    iou, adj = segment_targets(res, gt_ign, ignore_label=255, kept_only=False)
    assert iou[s] == 1.0 and adj[s] == 1.0
    assert np.isnan(iou[res.segments[0, 0]])     # nothing counted: 0 / 0
    with pytest.raises(ValueError, match="outside"):
        segment_targets(res, gt_ign)
    with pytest.raises(ValueError, match="entries"):
        segment_targets(res, gt[:-1])


# -- edge cases --------------------------------------------------------------------------


def test_empty_cloud_and_nothing_projected():
    cfg = RangeImageConfig.uniform(4, 8, 10.0, -20.0)
    for xyz in (np.zeros((0, 3)), pixel_points(cfg, [-5.0, 9.0], [1.0, 2.0])):
        probs = np.full((len(xyz), 3), 1 / 3, np.float32)
        res = compute_segments(xyz, probs, cfg)
        assert res.n_segments == 0 and res.features.shape == (0, 92)
        assert (res.point_segment == -1).all() and len(res.point_segment) == len(xyz)
        assert (res.segments == -1).all()
        iou, adj = segment_targets(res, np.zeros(len(xyz), int))
        assert len(iou) == len(adj) == 0
        assert to_points(res, np.zeros(0)).shape == (len(xyz),)
    with pytest.raises(ValueError, match="probs"):
        compute_segments(np.zeros((2, 3)), np.zeros((3, 2)), cfg)


def test_points_outside_the_field_of_view_change_nothing():
    cfg, xyz, probs, inten, gt = random_scene(5)
    proj = project(xyz, cfg)
    inside = proj.valid
    a = compute_segments(xyz[inside], probs[inside], cfg, intensity=inten[inside])
    b = compute_segments(xyz, probs, cfg, intensity=inten)
    assert proj.out_of_fov.sum() == 2
    np.testing.assert_array_equal(a.features, b.features)
    np.testing.assert_array_equal(b.point_segment[~inside], -1)
    np.testing.assert_array_equal(b.point_segment[inside], a.point_segment)


def test_ring_field_and_probability_layouts_give_the_same_result():
    cfg, xyz, probs, inten, gt = random_scene(2)
    proj = project(xyz, cfg)
    ring = np.where(proj.valid, proj.row, 99)
    a = compute_segments(xyz, probs, cfg, ring=ring, intensity=inten)
    b = compute_segments(xyz, probs, cfg, intensity=inten)
    np.testing.assert_array_equal(a.features, b.features)
    class_major = np.ascontiguousarray(probs.T)
    c = compute_segments(xyz, class_major.T, cfg, intensity=inten)
    d = compute_segments(xyz, probs.astype(np.float64), cfg, intensity=inten)
    np.testing.assert_array_equal(c.features, b.features)
    np.testing.assert_array_equal(d.features, b.features)
    np.testing.assert_array_equal(class_major, probs.T)      # the input is not modified


def test_min_points_and_to_points():
    cfg, xyz, probs, inten, gt = random_scene(7)
    res = compute_segments(xyz, probs, cfg, min_points=3)
    assert (res.size_projected[res.kept_ids] >= 3).all()
    assert (res.size_projected[~res.kept] < 3).all()
    vals = np.arange(len(res.kept_ids), dtype=float)
    per_point = to_points(res, vals)
    ps = res.point_segment
    for j in range(len(ps)):
        if ps[j] >= 0 and res.kept[ps[j]]:
            assert per_point[j] == np.flatnonzero(res.kept_ids == ps[j])[0]
        else:
            assert np.isnan(per_point[j])
    all_vals = np.arange(res.n_segments)
    np.testing.assert_array_equal(to_points(res, all_vals, fill=-1),
                                  np.where(ps >= 0, ps, -1))
    with pytest.raises(ValueError):
        to_points(res, np.zeros(res.n_segments + 1))


def test_label_periodic_matches_breadth_first_search():
    rng = np.random.default_rng(0)
    for _ in range(30):
        R, C = rng.integers(1, 7), rng.integers(1, 10)
        img = rng.integers(-1, 3, (R, C))
        lab, n = label_periodic(img)
        comps = components(img)
        assert n == len(comps)
        assert (lab[img < 0] == -1).all()
        for comp in comps:
            ids = {lab[p] for p in comp}
            assert len(ids) == 1
        # ids follow the first pixel in raster order
        firsts = [min(c) for c in comps]
        assert [lab[p] for p in sorted(firsts)] == list(range(n))


def test_no_segment_kept():
    cfg, xyz, probs, inten, gt = random_scene(3)
    res = compute_segments(xyz, probs, cfg, min_points=10_000)
    assert res.n_segments > 0 and len(res.kept_ids) == 0
    assert res.features.shape == (0, n_metrics(probs.shape[1]))
    assert segment_targets(res, gt)[0].shape == (0,)
    assert np.isnan(to_points(res, np.zeros(0))).all()


def test_simulated_frame_with_perfect_probabilities():
    # probabilities = the ground truth: predicted and ground-truth segments coincide
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64

    f = next(sequence_frames(3, 1))
    s = hdl64()
    cfg = RangeImageConfig.from_elevations(s.elevations_deg, s.columns)
    n = int(f.semantic.max()) + 1
    probs = np.full((len(f.xyz), n), 0.01 / (n - 1), np.float32)
    probs[np.arange(len(f.xyz)), f.semantic] = 0.99
    res = compute_segments(f.xyz, probs, cfg, ring=f.ring, intensity=f.intensity)
    assert res.size.sum() == cfg.rows * cfg.cols
    assert res.size_projected.sum() == res.delta.sum()
    assert res.n_points.sum() == (res.point_segment >= 0).sum() == res.projection.valid.sum()
    np.testing.assert_array_equal(res.point_class, f.semantic)
    iou, adj = segment_targets(res, f.semantic)
    assert len(iou) > 20
    np.testing.assert_array_equal(iou, 1.0)
    np.testing.assert_array_equal(adj, 1.0)
    f_ = res.features
    names = res.names
    assert np.isfinite(f_).all()
    Pc = f_[:, names.index("P_0"):]
    np.testing.assert_allclose(Pc.sum(axis=1), 1.0, rtol=1e-5)
    Nc = f_[:, names.index("N_0"):names.index("P_0")]
    np.testing.assert_allclose(Nc.sum(axis=1)[f_[:, names.index("S")] < 40000], 1.0)
    # the ring and the beam elevations give the same segments here
    res2 = compute_segments(f.xyz, probs, cfg, intensity=f.intensity)
    assert abs(res2.n_segments - res.n_segments) <= 0.02 * res.n_segments
