"""LidarMetaSeg metrics: hand-built range images with known values, and a brute-force
implementation of the paper's definitions (pixel sets, breadth-first search) that the
vectorized module must reproduce exactly on random clouds."""
import math

import numpy as np
import pytest

from lidar_quality_core.lms.projection import RangeImageConfig, project
from lidar_quality_core.lms.segment_metrics import (compute_segments, metric_names,
                                                    n_metrics, to_points)
from lidar_quality_core.lms.targets import segment_targets
from lms_images import brute, components, brute_targets, image_cloud, pixel_sets, pixel_points, random_scene


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


def test_layouts_give_identical_results_on_awkward_probabilities():
    # NaN, infinite, zero, negative, tiny and tied probabilities: every field of the result
    # is the same for row-major and class-major input (the compiled passes read either)
    import dataclasses

    cfg, xyz, probs, inten, gt = random_scene(4, R=8, C=24, n=5)
    rng = np.random.default_rng(4)
    p = probs.copy()
    k = rng.permutation(len(p))
    p[k[:4], 1] = np.nan
    p[k[4:8], 0] = np.inf
    p[k[8:12]] = 0.0
    p[k[12:16], 2] = -0.5
    p[k[16:20]] = np.float32(0.2)
    p[k[20:24], 3] = np.float32(1e-39)
    with np.errstate(all="ignore"):
        a = compute_segments(xyz, p, cfg, intensity=inten, min_points=1)
        b = compute_segments(xyz, np.ascontiguousarray(p.T).T, cfg, intensity=inten,
                             min_points=1)
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray):
            assert va.dtype == vb.dtype, f.name
            np.testing.assert_array_equal(va, vb, err_msg=f.name)
    assert np.isnan(a.point_E[k[:4]]).all() and (a.point_class[k[:4]] == 0).all()
    assert (a.point_class[k[16:20]] == 0).all() and (a.point_D[k[16:20]] == 1.0).all()


def test_read_only_inputs():
    # a message's buffer or a frozen array: read, never written (the compiled passes take
    # read-only arrays), in either layout and dtype
    cfg, xyz, probs, inten, gt = random_scene(6)
    want = compute_segments(xyz, probs, cfg, intensity=inten)

    def frozen(a):
        a = np.array(a)
        a.flags.writeable = False
        return a

    for x, p, i in ((xyz, probs, inten), (xyz.astype(np.float32), probs, inten.astype(np.float32)),
                    (frozen(xyz.T).T, frozen(probs.T).T, inten)):
        got = compute_segments(frozen(x), frozen(p), cfg, intensity=frozen(i))
        np.testing.assert_array_equal(got.point_segment, want.point_segment)
        np.testing.assert_array_equal(got.point_E, want.point_E)
        if x.dtype == xyz.dtype:
            np.testing.assert_array_equal(got.features, want.features)
        else:
            np.testing.assert_allclose(got.features, want.features, rtol=1e-5, atol=1e-6)


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


def test_record_run_reads_records_and_leaves_other_layouts_to_the_view():
    from lidar_quality_core.lms.segment_metrics import _record_run
    rng = np.random.default_rng(0)
    rec = rng.random((50, 9)).astype(np.float32)
    view = rec[:, 3:7]                          # 4 classes inside 9-float records
    run, step = _record_run(view)
    assert step == 9 and not run.flags.writeable and np.shares_memory(run, rec)
    assert len(run) == 49 * 9 + 4               # ends at the last probability
    got = np.stack([run[i * step:i * step + 4] for i in range(50)])
    np.testing.assert_array_equal(got, view)
    # class-major, float64, a byte-misaligned view, an empty array: no run
    bytes_ = np.zeros(50 * 36 + 1, np.uint8)
    odd = np.ndarray((50, 4), np.float32, buffer=bytes_, offset=1, strides=(36, 4))
    for other in (np.ascontiguousarray(view.T).T, view.astype(np.float64), odd,
                  view[:0]):
        assert len(_record_run(other)[0]) == 0
