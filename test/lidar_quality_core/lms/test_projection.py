import math

import numpy as np
import pytest

from lidar_quality_core.lms.projection import (RangeImageConfig, project, shift, window_reduce,
                                               window_stats)


def _point(az_deg, el_deg, r=10.0):
    a, e = np.radians(az_deg), np.radians(el_deg)
    return [r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e)]


UNI = RangeImageConfig.uniform(rows=4, cols=8, fov_up_deg=10.0, fov_down_deg=-30.0)


def test_config_validation_and_edges():
    cfg = RangeImageConfig.from_elevations([2.0, 0.0, -4.0], cols=16)
    np.testing.assert_allclose(cfg.row_edges_deg, [3.0, 1.0, -2.0, -6.0])
    np.testing.assert_allclose(UNI.row_edges_deg, [10, 0, -10, -20, -30])
    with pytest.raises(ValueError, match="decreasing"):
        RangeImageConfig.from_elevations([0.0, 1.0])
    with pytest.raises(ValueError, match="either"):
        RangeImageConfig(rows=2, cols=4)
    with pytest.raises(ValueError, match="fov_up"):
        RangeImageConfig.uniform(2, 4, -5.0, 5.0)


def test_known_points_land_in_known_pixels():
    # columns: 8 columns of 45 deg, col 0 = [180, 135) deg, clockwise; forward (0 deg) is
    # the left edge of col 4, just right of forward (-1 deg) col 4, just left (+1) col 3
    pts = np.array([_point(179, 5), _point(0.5, -5), _point(-0.5, -15), _point(-179, -25),
                    _point(90.5, 5), _point(-90.5, 5)])
    p = project(pts, UNI)
    np.testing.assert_array_equal(p.row, [0, 1, 2, 3, 0, 0])
    np.testing.assert_array_equal(p.col, [0, 3, 4, 7, 1, 6])
    np.testing.assert_array_equal(p.pixel, p.row * 8 + p.col)
    assert p.valid.all() and not p.out_of_fov.any()
    for i in range(len(pts)):
        assert p.index[p.row[i], p.col[i]] == i
    assert p.mask.sum() == len(pts)
    np.testing.assert_allclose(p.range, 10.0, rtol=1e-6)


def test_col_matches_the_simulator_firing_azimuths():
    from lidar_sim.sensor import beam_directions, hdl64

    s = hdl64(columns=256)
    cfg = RangeImageConfig.from_elevations(s.elevations_deg, s.columns)
    d = beam_directions(s).reshape(-1, 3) * 20.0
    p = project(d, cfg)
    rows, cols = np.divmod(np.arange(len(d)), s.columns)
    np.testing.assert_array_equal(p.row, rows)
    np.testing.assert_array_equal(p.col, cols)


def test_ring_and_elevation_agree_on_a_simulated_frame():
    from lidar_sim.frames import split_frames
    from lidar_sim.sensor import hdl64

    f = next(split_frames("reference_test", sequences=[0], frames=30))
    s = hdl64()
    cfg = RangeImageConfig.from_elevations(s.elevations_deg, s.columns)
    a = project(f.xyz, cfg, ring=f.ring)
    b = project(f.xyz, cfg)
    assert a.valid.all()
    assert (a.row == b.row).mean() > 0.999
    np.testing.assert_array_equal(a.col, b.col)
    # the simulator fires each (ring, column) once: every point keeps its own pixel
    assert a.winner.all()


def test_nearest_point_wins_a_pixel():
    pts = np.array([_point(10, -5, 20.0), _point(10.1, -5.1, 5.0), _point(10.2, -5, 12.0),
                    _point(-100, -5, 7.0)])
    p = project(pts, UNI)
    assert len(set(p.pixel[:3])) == 1
    assert p.index[p.row[0], p.col[0]] == 1
    np.testing.assert_array_equal(p.winner, [False, True, False, True])
    # the same under any point order
    perm = np.array([2, 3, 1, 0])
    q = project(pts[perm], UNI)
    assert perm[q.index[p.row[0], p.col[0]]] == 1
    # gather / at_points round trip the winner's values
    img = p.gather(np.arange(4.0))
    assert img[p.row[0], p.col[0]] == 1.0 and np.isnan(img).sum() == 32 - 2
    np.testing.assert_array_equal(p.at_points(img), [1, 1, 1, 3])


def test_equal_range_tie_goes_to_the_lowest_index():
    pts = np.array([_point(10, -5, 8.0)] * 3)
    for perm in ([0, 1, 2], [2, 0, 1]):
        p = project(pts[perm], UNI)
        assert p.index[p.row[0], p.col[0]] == 0


def test_dense_contested_pixels_match_the_rule_point_by_point():
    """Most pixels contested (a dense scan): every pixel holds its smallest-range point,
    ties to the lowest index, as a loop over the points finds it."""
    rng = np.random.default_rng(3)
    cfg = RangeImageConfig.uniform(8, 32, 10.0, -20.0)
    n = 3000
    pts = rng.normal(0, 1, (n, 3)) * [20, 20, 2]
    pts[::7] = pts[1::7][: len(pts[::7])]            # exact duplicates: equal ranges
    p = project(pts, cfg)
    want = np.full(cfg.rows * cfg.cols, -1)
    best = np.full(cfg.rows * cfg.cols, np.inf)
    r = np.linalg.norm(pts, axis=1)
    for i in range(n):
        if p.valid[i] and r[i] < best[p.pixel[i]]:
            best[p.pixel[i]], want[p.pixel[i]] = r[i], i
    np.testing.assert_array_equal(p.index.reshape(-1), want)


def test_ring_gives_the_row():
    pts = np.array([_point(10, 5), _point(10, 5), _point(10, 5)])
    p = project(pts, UNI, ring=np.array([0, 3, 4], np.uint16))
    np.testing.assert_array_equal(p.row, [0, 3, -1])
    np.testing.assert_array_equal(p.out_of_fov, [False, False, True])
    with pytest.raises(ValueError, match="ring"):
        project(pts, UNI, ring=[0, 1])


def test_empty_cloud():
    for xyz in (np.zeros((0, 3), np.float32), np.array([])):
        p = project(xyz, UNI)
        assert len(p) == 0 and p.index.shape == (4, 8) and (p.index == -1).all()
        assert p.gather(np.zeros(0)).shape == (4, 8)
        assert p.at_points(np.zeros((4, 8))).shape == (0,)


def test_nan_and_out_of_fov_points_are_flagged_not_projected():
    pts = np.array([_point(0, 5), [np.nan, 1, 1], [np.inf, 0, 0], _point(0, 20),
                    _point(0, -31), [0.0, 0.0, 0.0], _point(45, -29.9)])
    p = project(pts, UNI)
    np.testing.assert_array_equal(p.valid, [True, False, False, False, False, True, True])
    np.testing.assert_array_equal(p.out_of_fov, [False, False, False, True, True, False, False])
    assert (p.row[~p.valid] == -1).all() and (p.col[~p.valid] == -1).all()
    assert (p.pixel[~p.valid] == -1).all()
    assert np.isnan(p.range[1]) and np.isnan(p.range[2])
    assert p.mask.sum() == 3
    vals = p.at_points(np.ones((4, 8)), fill=-7.0)
    np.testing.assert_array_equal(vals, [1, -7, -7, -7, -7, 1, 1])


def test_seam_wraps_around():
    img = np.zeros((3, 8))
    img[1, 0] = 1.0
    # the pixel right of col 7 is col 0 (behind the car)
    assert shift(img, 0, 1)[1, 7] == 1.0
    assert shift(img, 0, -1)[1, 1] == 1.0
    # rows do not wrap
    assert np.isnan(shift(img, 2, 0)[1]).all()
    s = window_reduce(img, 3, "sum")
    np.testing.assert_array_equal(np.flatnonzero(s[1]), [0, 1, 7])
    np.testing.assert_array_equal(np.flatnonzero(s[:, 7]), [0, 1, 2])
    # neighbour pixels of a point in the last column
    pts = np.array([_point(-179, 5)])
    p = project(pts, UNI)
    assert p.col[0] == 7
    assert p.neighbour_pixels(0, 1)[0] == 0 * 8 + 0
    assert p.neighbour_pixels(-1, 0)[0] == -1  # above row 0: outside


def test_window_reduce_matches_brute_force():
    rng = np.random.default_rng(0)
    img = rng.normal(size=(6, 10))
    for size in (1, 3, (3, 5), (5, 3)):
        h, w = (size, size) if np.isscalar(size) else size
        for op, fn, neutral in (("sum", np.sum, 0.0), ("max", np.max, -np.inf),
                                ("min", np.min, np.inf)):
            got = window_reduce(img, size, op)
            pad = np.pad(img, ((h // 2, h // 2), (0, 0)), constant_values=neutral)
            want = np.empty_like(img)
            for r in range(6):
                for c in range(10):
                    cols = np.arange(c - w // 2, c + w // 2 + 1) % 10
                    want[r, c] = fn(pad[r:r + h][:, cols])
            np.testing.assert_allclose(got, want, err_msg=f"{op} {size}")
    with pytest.raises(ValueError):
        window_reduce(img, 2)


def test_window_stats_ignore_missing_pixels():
    img = np.full((3, 4), np.nan)
    img[1, 1], img[1, 2] = 1.0, 3.0
    ws = window_stats(img, 3)
    assert ws.count[1, 1] == 2 and ws.mean[1, 1] == 2.0 and ws.std[1, 1] == 1.0
    assert ws.min[0, 0] == 1.0 and ws.max[0, 0] == 1.0   # col 0 sees col 1 only
    assert ws.count[0, 3] == 1 and ws.max[0, 3] == 3.0   # col 3 sees col 2 and col 0
    valid = np.ones((3, 4), bool)
    valid[1, 2] = False
    assert window_stats(img, 3, valid).count[1, 1] == 1
    allnan = window_stats(np.full((2, 2), np.nan), 3)
    assert np.isnan(allnan.mean).all() and (allnan.count == 0).all()


def test_integer_values_keep_their_dtype_unless_the_fill_needs_more():
    p = project(np.array([_point(0, 5), [np.nan, 0, 0]]), UNI)
    g = p.gather(np.array([5, 6]), fill=-1)
    assert g.dtype == np.int64 and g.max() == 5 and (g == -1).sum() == 31
    np.testing.assert_array_equal(p.at_points(g, fill=-1), [5, -1])
    f = p.at_points(g)  # NaN fill: widened to float
    assert f.dtype.kind == "f" and f[0] == 5 and np.isnan(f[1])


_libm_asin = np.frompyfunc(math.asin, 1, 1)
_libm_atan2 = np.frompyfunc(math.atan2, 2, 1)


def numpy_project(xyz, cfg, ring=None):
    """Plain numpy reference of :func:`project` (its implementation before the compiled
    kernels): (row, col, pixel, range, valid, out_of_fov, index).

    Elevations and azimuths with libm's asin and atan2 point by point: :func:`project` is
    libm's on every machine, numpy's float64 ``arcsin`` / ``arctan2`` only on one without
    AVX-512 (with it numpy runs its own SIMD loops, a last bit away from libm for about 8 %
    of inputs: measured on a 2-vCPU Intel Xeon, 2026-12-05)."""
    xyz = np.asarray(xyz).reshape(-1, 3)
    n = len(xyz)
    R, C = cfg.rows, cfg.cols
    x, y, z = (xyz[:, k].astype(np.float64) for k in range(3))
    with np.errstate(invalid="ignore", over="ignore"):
        rng = np.sqrt(x * x + y * y + z * z)
    finite = np.isfinite(rng)
    row = np.full(n, -1, dtype=np.int32)
    if ring is not None:
        ring = np.asarray(ring).reshape(-1)
        ok = finite & (ring >= 0) & (ring < R)
        row[ok] = ring[ok]
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            el = np.degrees(_libm_asin(np.clip(z / np.where(rng > 0, rng, 1.0), -1.0, 1.0))
                            .astype(np.float64))
        r_idx = np.searchsorted(-cfg.row_edges_deg, -el[finite], side="right") - 1
        r_idx[(r_idx < 0) | (r_idx >= R)] = -1
        row[finite] = r_idx
    valid = row >= 0
    u = _libm_atan2(y, x).astype(np.float64) * (-0.5 * C / np.pi) + 0.5 * C
    col = np.full(n, -1, dtype=np.int32)
    col[valid] = np.floor(u[valid]).astype(np.int32) % np.int32(C)
    pixel = np.where(valid, row.astype(np.int64) * C + col, -1)
    # nearest point per pixel: smallest range, then the lowest index
    order = np.lexsort((np.arange(n), rng))
    order = order[valid[order]]
    index = np.full(R * C, -1, dtype=np.int32)
    first = np.unique(pixel[order], return_index=True)[1]
    index[pixel[order][first]] = order[first]
    return (row, col, pixel, np.where(finite, rng, np.nan).astype(np.float32), valid,
            finite & ~valid, index.reshape(R, C))


def adversarial_cloud(n, cfg, seed):
    """Random points plus every special case of the projection: NaN / inf, the origin,
    points above and below the field of view, azimuth exactly +-pi and +-pi/2, straight up,
    duplicates and equal ranges, elevations exactly on the bin edges, azimuths exactly on
    the column edges."""
    rng = np.random.default_rng(seed)
    p = rng.normal(0, 1, (n, 3)) * [30, 30, 3]
    k = n // 16
    p[0:k] = np.nan
    p[k:2 * k, rng.integers(0, 3)] = rng.choice([np.inf, -np.inf])
    p[2 * k:2 * k + 5] = 0.0
    p[2 * k + 5:3 * k, 2] = rng.choice([1e3, -1e3], k - 5)
    p[3 * k:4 * k, 1] = rng.choice([0.0, -0.0], k)                 # azimuth +-pi or 0
    p[3 * k:4 * k, 0] = -np.abs(p[3 * k:4 * k, 0])
    p[4 * k:5 * k, 0] = 0.0                                          # azimuth +-pi/2
    p[5 * k:5 * k + 5, :2] = 0.0                                     # straight up / down
    p[6 * k:7 * k] = p[7 * k:8 * k]                                  # duplicates
    p[8 * k:9 * k] = p[9 * k:10 * k][:, [1, 0, 2]]                   # equal ranges
    e = np.radians(cfg.row_edges_deg[rng.integers(0, cfg.rows + 1, k)])
    az = rng.uniform(-np.pi, np.pi, k)
    p[10 * k:11 * k] = 10 * np.c_[np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)]
    az = -np.pi + 2 * np.pi * rng.integers(0, cfg.cols + 1, k) / cfg.cols
    p[11 * k:12 * k] = 10 * np.c_[np.cos(az), np.sin(az), rng.normal(0, 0.3, k)]
    return p[rng.permutation(n)]


CONFIGS = [RangeImageConfig.from_elevations(np.r_[2.0:-8.5:-1 / 3, -9.0:-25.0:-0.5], 256),
           RangeImageConfig.uniform(16, 128, 15.0, -15.0), RangeImageConfig.uniform(1, 7, 5, -5),
           RangeImageConfig.uniform(5, 1, 10, -10), RangeImageConfig.uniform(3000, 16, 10, -10),
           RangeImageConfig.uniform(2, 8, 5e-324, -5e-324), UNI]


@pytest.mark.parametrize("cfg", CONFIGS, ids=lambda c: f"{c.rows}x{c.cols}")
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_matches_the_numpy_reference_bit_for_bit(cfg, dtype):
    for seed in range(3):
        with np.errstate(over="ignore"):
            xyz = adversarial_cloud(4000, cfg, seed).astype(dtype)
        ring = np.random.default_rng(seed).integers(-2, cfg.rows + 2, len(xyz))
        for r, pts in ((None, xyz), (ring, xyz), (ring.astype(np.uint16) % 70, xyz),
                       (None, np.asfortranarray(xyz)), (ring + 0.5, xyz[::-1])):
            got = project(pts, cfg, r)
            want = numpy_project(pts, cfg, r)
            for name, w in zip(("row", "col", "pixel", "range", "valid", "out_of_fov",
                                "index"), want):
                g = getattr(got, name)
                assert g.dtype == w.dtype, name
                np.testing.assert_array_equal(g, w, err_msg=f"{name} seed {seed}")


def test_dense_cloud_matches_the_numpy_reference():
    """Many more points than pixels: nearly every pixel contested, equal ranges included."""
    cfg = RangeImageConfig.uniform(16, 64, 5.0, -15.0)
    rng = np.random.default_rng(7)
    xyz = (rng.normal(0, 1, (20000, 3)) * [20, 20, 2]).astype(np.float32)
    xyz[::3] = xyz[1::3][: len(xyz[::3])]
    ring = rng.integers(0, 16, len(xyz))
    for r in (None, ring):
        got, want = project(xyz, cfg, r), numpy_project(xyz, cfg, r)
        np.testing.assert_array_equal(got.index, want[6])
        np.testing.assert_array_equal(got.pixel, want[2])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_approximate_column_coordinates_stay_well_inside_the_exact_recheck_margin(dtype):
    """The vectorized atan2 is within a hundredth of the margin near column edges where
    project recomputes libm's atan2 (so every column is libm's); NaN only where libm's
    atan2 is redone anyway (origin, non-finite)."""
    from lidar_quality_core.lms import projection as pj

    rng = np.random.default_rng(3)
    x, y = (rng.normal(0, 1, 200_000) * 10.0 ** rng.uniform(-30, 30, 200_000)).astype(dtype), \
        rng.normal(0, 30, 200_000).astype(dtype)
    y[:1000] = x[:1000] * dtype(np.tan(0.3))                        # rays, all octants
    x[1000:1010] = y[1000:1010] = 0.0
    C = 4096
    scale, offset = -0.5 * C / np.pi, 0.5 * C
    u = np.empty(len(x))
    pj._column_coordinates(x, y, scale, offset, u)
    ref = np.arctan2(y, x, dtype=np.float64) * scale + offset
    ok = np.isfinite(u)
    assert not ok[1000:1010].any() and ok[1010:].all()
    err = np.abs(u[ok] - ref[ok])
    err = np.minimum(err, np.abs(err - C))                         # +pi / -pi: the same edge
    assert err.max() < pj._EDGE_MARGIN / 100


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_approximate_elevations_stay_well_inside_the_exact_recheck_margin(dtype):
    from lidar_quality_core.lms import projection as pj

    rng = np.random.default_rng(4)
    xyz = rng.normal(0, 1, (200_000, 3)) * [30, 30, 3]
    xyz[:1000, :2] *= 1e-9                                         # near the poles
    xyz[1000:1010] = 0.0
    x, y, z = (np.ascontiguousarray(xyz[:, k].astype(dtype)) for k in range(3))
    el = np.empty(len(x))
    pj._elevations(x, y, z, el)
    x, y, z = (v.astype(np.float64) for v in (x, y, z))
    r = np.sqrt(x * x + y * y + z * z)
    ref = np.arcsin(np.clip(z / np.where(r > 0, r, 1.0), -1.0, 1.0))
    assert np.degrees(np.abs(el - ref)).max() < pj._EDGE_MARGIN / 100
