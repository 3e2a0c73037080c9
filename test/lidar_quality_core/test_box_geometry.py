"""Tests for lidar_quality_core.box_geometry (corners, points in boxes, segment stats)."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lidar_quality_core import box_geometry as bg
from lidar_quality_core.box_geometry import (bev_corners, corners_3d, count_points_in_boxes,
                                             points_in_boxes, segment_stats)


# ---------------------------------------------------------------- references
def ref_inside(points, boxes, margin=0.0):
    """Brute-force (M, N) membership via explicit rotation matrices (chunked over boxes)."""
    p = np.asarray(points, dtype=np.float64)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    out = np.zeros((len(p), len(b)), dtype=bool)
    for j, (x, y, z, l, w, h, yaw) in enumerate(b):
        if not (np.all(np.isfinite(b[j])) and l > 0 and w > 0 and h > 0):
            continue
        rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        with np.errstate(invalid="ignore", over="ignore"):
            loc = (p[:, :2] - [x, y]) @ rot  # = R^T (p - c) row-wise
            out[:, j] = ((np.abs(loc[:, 0]) <= l / 2 + margin)
                         & (np.abs(loc[:, 1]) <= w / 2 + margin)
                         & (np.abs(p[:, 2] - z) <= h / 2 + margin))
    return out


def csr_to_dense(offsets, idx, m):
    n = len(offsets) - 1
    out = np.zeros((m, n), dtype=bool)
    for j in range(n):
        seg = idx[offsets[j]:offsets[j + 1]]
        assert np.all(np.diff(seg) > 0), "point_index must be strictly ascending per box"
        out[seg, j] = True
    return out


def check_against_ref(points, boxes, margin=0.0, exact=True):
    off, idx = points_in_boxes(points, boxes, margin=margin)
    n = len(np.asarray(boxes).reshape(-1, 7))
    assert off.shape == (n + 1,) and off[0] == 0 and off[-1] == len(idx)
    assert np.issubdtype(idx.dtype, np.integer)
    got = csr_to_dense(off, idx, len(points))
    ref = ref_inside(points, boxes, margin)
    if exact:
        np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(count_points_in_boxes(points, boxes, margin), np.diff(off))
    return got, ref


def random_scene(rng, m=3000, n=60, spread=30.0, dtype=np.float64):
    boxes = np.column_stack([
        rng.uniform(-spread, spread, (n, 2)), rng.uniform(-1, 1, n),
        rng.uniform(0.3, 6.0, n), rng.uniform(0.3, 3.0, n), rng.uniform(0.5, 3.0, n),
        rng.uniform(-np.pi, np.pi, n)])
    # half the points near boxes so that many are inside
    near = boxes[rng.integers(0, n, m // 2), :3] + rng.normal(0, 1.5, (m // 2, 3))
    far = np.column_stack([rng.uniform(-spread - 5, spread + 5, (m - m // 2, 2)),
                           rng.uniform(-2, 2, m - m // 2)])
    return np.concatenate([near, far]).astype(dtype), boxes


# ---------------------------------------------------------------- corners
def test_bev_corners_axis_aligned_exact_and_ccw():
    c = bev_corners([[1.0, 2.0, 0.0, 4.0, 2.0, 1.0, 0.0]])[0]
    np.testing.assert_array_equal(c, [[3, 3], [-1, 3], [-1, 1], [3, 1]])
    rng = np.random.default_rng(0)
    _, boxes = random_scene(rng, 10, 50)
    cs = bev_corners(boxes)
    x, y = cs[..., 0], cs[..., 1]
    area = 0.5 * np.sum(x * np.roll(y, -1, 1) - y * np.roll(x, -1, 1), axis=1)
    np.testing.assert_allclose(area, boxes[:, 3] * boxes[:, 4], rtol=1e-12)  # > 0: CCW
    # corner 0 is front-left: along +heading and +lateral from the centre
    head = np.column_stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6])])
    lat = np.column_stack([-np.sin(boxes[:, 6]), np.cos(boxes[:, 6])])
    rel = cs[:, 0] - boxes[:, :2]
    np.testing.assert_allclose(np.sum(rel * head, 1), boxes[:, 3] / 2, atol=1e-12)
    np.testing.assert_allclose(np.sum(rel * lat, 1), boxes[:, 4] / 2, atol=1e-12)


def test_bev_corners_rotation_90():
    c = bev_corners([[0.0, 0.0, 0.0, 4.0, 2.0, 1.0, np.pi / 2]])[0]
    np.testing.assert_allclose(c, [[-1, 2], [-1, -2], [1, -2], [1, 2]], atol=1e-12)


def test_corners_3d_layout():
    b = np.array([[1.0, 2.0, 3.0, 4.0, 2.0, 6.0, 0.3]])
    c3 = corners_3d(b)
    assert c3.shape == (1, 8, 3)
    np.testing.assert_allclose(c3[0, :4, :2], bev_corners(b)[0])
    np.testing.assert_allclose(c3[0, 4:, :2], bev_corners(b)[0])
    np.testing.assert_allclose(c3[0, :4, 2], 0.0)
    np.testing.assert_allclose(c3[0, 4:, 2], 6.0)
    # every corner lies on the closed box
    assert count_points_in_boxes(c3[0], b, margin=1e-9)[0] == 8
    assert count_points_in_boxes(c3[0], b, margin=-1e-9)[0] == 0


def test_empty_inputs_and_shapes():
    off, idx = points_in_boxes(np.zeros((0, 3)), np.zeros((3, 7)))
    np.testing.assert_array_equal(off, [0, 0, 0, 0])
    assert idx.shape == (0,)
    off, idx = points_in_boxes(np.zeros((5, 3)), np.zeros((0, 7)))
    np.testing.assert_array_equal(off, [0])
    assert bev_corners(np.zeros((0, 7))).shape == (0, 4, 2)
    assert corners_3d(np.zeros((0, 7))).shape == (0, 8, 3)
    with pytest.raises(ValueError):
        points_in_boxes(np.zeros((5, 2)), np.zeros((1, 7)))
    with pytest.raises(ValueError):
        points_in_boxes(np.zeros((5, 3)), np.zeros((1, 6)))


# ---------------------------------------------------------------- points in boxes
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_points_in_boxes_matches_brute_force(seed, dtype):
    rng = np.random.default_rng(seed)
    pts, boxes = random_scene(rng, dtype=dtype)
    got, _ = check_against_ref(pts, boxes)
    assert got.sum() > 100  # the scene really exercises membership
    assert (got.sum(1) > 1).any()  # and overlapping boxes


def test_points_in_boxes_synthetic_frame():
    from lidar_quality_core.synthetic import synthetic_frame
    f = synthetic_frame(n_points=20_000, n_objects=12, n_proposals=80, seed=3)
    boxes = np.concatenate([f.detections, f.proposals])
    got, _ = check_against_ref(f.points, boxes)
    assert got.sum() > 500


def test_boundary_is_inclusive_axis_aligned():
    # exactly representable values: the boundary decision is unambiguous
    box = np.array([[1.0, 2.0, 0.5, 4.0, 2.0, 1.0, 0.0]])
    on = np.array([[3.0, 2.0, 0.5], [-1.0, 2.0, 0.5], [1.0, 3.0, 0.5], [1.0, 1.0, 0.5],
                   [1.0, 2.0, 1.0], [1.0, 2.0, 0.0], [3.0, 3.0, 1.0], [-1.0, 1.0, 0.0]])
    off_pts = on + np.array([[2.0**-20, 0, 0], [-(2.0**-20), 0, 0], [0, 2.0**-20, 0],
                             [0, -(2.0**-20), 0], [0, 0, 2.0**-20], [0, 0, -(2.0**-20)],
                             [2.0**-20, 0, 0], [0, -(2.0**-20), 0]])
    for dt in (np.float32, np.float64):
        assert count_points_in_boxes(on.astype(dt), box)[0] == len(on)
        assert count_points_in_boxes(off_pts.astype(dt), box)[0] == 0
    check_against_ref(np.concatenate([on, off_pts]), box)


def test_boundary_points_of_rotated_boxes_with_margin():
    rng = np.random.default_rng(5)
    _, boxes = random_scene(rng, 10, 30)
    # points on each face centre and each corner, nudged inwards / outwards
    for sign, expect in ((-1, True), (1, False)):
        c3 = corners_3d(boxes)
        ctr = boxes[:, None, :3]
        pts = c3 + sign * 1e-6 * (c3 - ctr) / np.linalg.norm(c3 - ctr, axis=2, keepdims=True)
        for j in range(len(boxes)):
            assert ref_inside(pts[j], boxes[j:j + 1]).sum() == (8 if expect else 0)
            assert count_points_in_boxes(pts[j], boxes[j:j + 1])[0] == (8 if expect else 0)


def test_margin_grows_and_shrinks():
    rng = np.random.default_rng(7)
    pts, boxes = random_scene(rng, 2000, 40)
    for margin in (0.25, -0.1, 1.0):
        check_against_ref(pts, boxes, margin=margin)
    assert (count_points_in_boxes(pts, boxes, 0.3) >= count_points_in_boxes(pts, boxes)).all()
    # a margin that removes the whole box: nothing inside
    tiny = boxes.copy()
    tiny[:, 3:6] = 0.1
    assert count_points_in_boxes(pts, tiny, margin=-0.2).sum() == 0


def test_invalid_boxes_contain_nothing():
    pts = np.random.default_rng(1).uniform(-3, 3, (500, 3))
    pts[0] = 0.0  # exactly on the degenerate boxes' centre planes
    boxes = np.array([
        [0, 0, 0, 2, 2, 2, 0.1],          # valid
        [0, 0, 0, 0, 2, 2, 0.0],          # zero length
        [0, 0, 0, 2, -1, 2, 0.0],         # negative width
        [0, 0, 0, 2, 2, 0, 0.0],          # zero height
        [np.nan, 0, 0, 2, 2, 2, 0.0],     # NaN centre
        [0, 0, 0, 2, 2, 2, np.nan],       # NaN yaw
        [0, 0, 0, np.inf, 2, 2, 0.0],     # infinite size
    ])
    counts = count_points_in_boxes(pts, boxes)
    assert counts[0] > 0
    np.testing.assert_array_equal(counts[1:], 0)
    check_against_ref(pts, boxes)


def test_nan_and_inf_points_are_never_inside():
    boxes = np.array([[0, 0, 0, 4, 4, 4, 0.0], [1, 1, 0, 2, 2, 2, 0.7]])
    pts = np.array([[np.nan, 0, 0], [0, np.nan, 0], [0, 0, np.nan], [np.inf, 0, 0],
                    [-np.inf, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [np.nan] * 3,
                    [0.5, 0.5, 0.5], [1e30, -1e30, 0], [3e38, 3e38, 3e38]])
    for dt in (np.float32, np.float64):
        off, idx = points_in_boxes(pts.astype(dt), boxes)
        assert set(idx.tolist()) == {8}
        np.testing.assert_array_equal(np.diff(off), [1, 1])


@pytest.mark.parametrize("offset", [1e5, 1e7, 1e12])
def test_huge_coordinates(offset):
    rng = np.random.default_rng(11)
    pts, boxes = random_scene(rng, 2000, 30, spread=20)
    pts = pts + [offset, -offset, 0.0]
    boxes = boxes.copy()
    boxes[:, :2] += [offset, -offset]
    got, ref = check_against_ref(pts, boxes, exact=False)
    # far from the origin the float rounding of the two formulas may differ by an ulp at
    # the boundary only: allow a handful of disagreements
    assert (got != ref).sum() <= 2
    assert ref.sum() > 100


def test_scattered_and_giant_boxes():
    rng = np.random.default_rng(3)
    pts, boxes = random_scene(rng, 3000, 40)
    extra = np.array([
        [0, 0, 0, 500.0, 400.0, 50.0, 0.3],        # giant box: brute-force path
        [1e9, 1e9, 0, 2, 2, 2, 0.0],               # far away box stretches the grid
        [-1e9, 5.0, 0, 2, 2, 2, 0.0],
        [1e16, 0, 0, 1, 1, 1, 0.0],                # absurd centre: brute-force path
        [0, 0, 0, 1.7e308, 1.7e308, 1e300, 0.3],   # AABB overflows to inf
    ])
    boxes = np.concatenate([boxes, extra])
    pts = np.concatenate([pts, [[1e9, 1e9, 0.5], [-1e9, 5.5, 0], [1e16, 0.2, 0]]])
    got, _ = check_against_ref(pts, boxes)
    assert got[:, -5].sum() == len(pts) - 3
    assert got[-3, -4] and got[-2, -3] and got[-1, -2]
    assert got[:, -1].all()


def test_many_tiny_boxes_beyond_int16():
    # > 32767 boxes: the per-box ordering cannot use 16-bit sort keys
    rng = np.random.default_rng(4)
    n = 33_000
    xy = rng.uniform(-100, 100, (n, 2))
    boxes = np.column_stack([xy, np.zeros(n), np.full((n, 3), 0.5), rng.uniform(-3, 3, n)])
    pts = np.column_stack([xy[-3000:] + rng.normal(0, 0.2, (3000, 2)), np.zeros(3000)])
    off, idx = points_in_boxes(pts, boxes)
    assert len(off) == n + 1
    sel = np.concatenate([np.arange(200), np.arange(n - 800, n)])  # incl. high indices
    ref = ref_inside(pts, boxes[sel])
    for col, j in enumerate(sel):
        np.testing.assert_array_equal(idx[off[j]:off[j + 1]], np.flatnonzero(ref[:, col]))
    assert ref.sum() > 300


@pytest.mark.parametrize("consts", [
    dict(_MAX_CELL_ENTRIES=50, _MAX_CELLS=64, _MAX_CELLS_PER_AXIS=5),
    dict(_BIG_BOX_CELLS=2, _CELL_FACTOR=0.05),
    dict(_CELL_FACTOR=3.0),
])
def test_grid_limits_do_not_change_results(monkeypatch, consts):
    for k, v in consts.items():
        monkeypatch.setattr(bg, k, v)
    rng = np.random.default_rng(9)
    pts, boxes = random_scene(rng, 1500, 50)
    boxes[:5, 3:5] *= 8  # a few big boxes among small ones
    check_against_ref(pts, boxes)
    check_against_ref(pts.astype(np.float32), boxes)


def test_points_in_several_boxes_listed_in_each():
    boxes = np.array([[0, 0, 0, 2, 2, 2, 0.0], [0.5, 0, 0, 2, 2, 2, 0.4], [5, 5, 5, 1, 1, 1, 0]])
    pts = np.array([[0.2, 0.1, 0.0], [0.9, 0.0, 0.0], [-0.9, 0, 0], [5, 5, 5]])
    off, idx = points_in_boxes(pts, boxes)
    np.testing.assert_array_equal(idx[off[0]:off[1]], [0, 1, 2])
    np.testing.assert_array_equal(idx[off[1]:off[2]], [0, 1])
    np.testing.assert_array_equal(idx[off[2]:off[3]], [3])


def test_integer_points_accepted():
    off, idx = points_in_boxes(np.array([[0, 0, 0], [5, 5, 5]]), [[0, 0, 0, 1, 1, 1, 0]])
    np.testing.assert_array_equal(idx, [0])


# ---------------------------------------------------------------- rigid motion (property)
def _clear_of_boundary(points, boxes, eps):
    """Mask of points at least ``eps`` away from every face of every box (in local frame)."""
    ok = np.ones(len(points), dtype=bool)
    for x, y, z, l, w, h, yaw in boxes:
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy = points[:, 0] - x, points[:, 1] - y
        loc = np.abs(np.column_stack([c * dx + s * dy, -s * dx + c * dy, points[:, 2] - z]))
        ok &= np.all(np.abs(loc - [l / 2, w / 2, h / 2]) > eps, axis=1)
    return ok


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), theta=st.floats(-10, 10),
       tx=st.floats(-1e4, 1e4), ty=st.floats(-1e4, 1e4), tz=st.floats(-50, 50),
       f32=st.booleans())
def test_counts_invariant_under_rigid_motion(seed, theta, tx, ty, tz, f32):
    rng = np.random.default_rng(seed)
    pts, boxes = random_scene(rng, 400, 15, spread=10)
    pts = pts[_clear_of_boundary(pts, boxes, 1e-3)]
    c, s = np.cos(theta), np.sin(theta)
    moved = np.column_stack([c * pts[:, 0] - s * pts[:, 1] + tx,
                             s * pts[:, 0] + c * pts[:, 1] + ty, pts[:, 2] + tz])
    mb = boxes.copy()
    mb[:, 0] = c * boxes[:, 0] - s * boxes[:, 1] + tx
    mb[:, 1] = s * boxes[:, 0] + c * boxes[:, 1] + ty
    mb[:, 2] += tz
    mb[:, 6] += theta
    dt = np.float32 if f32 else np.float64
    if f32:  # keep float32 rounding (~1e-3 m at 1e4 m) below the clearance
        pts = pts[_clear_of_boundary(pts, boxes, 5e-2)]
        moved = np.column_stack([c * pts[:, 0] - s * pts[:, 1] + tx,
                                 s * pts[:, 0] + c * pts[:, 1] + ty, pts[:, 2] + tz])
    o1, i1 = points_in_boxes(pts.astype(dt), boxes)
    o2, i2 = points_in_boxes(moved.astype(dt), mb)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(i1, i2)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 25), m=st.integers(0, 300),
       margin=st.sampled_from([0.0, 0.1, -0.05]))
def test_random_scenes_match_reference_property(seed, n, m, margin):
    rng = np.random.default_rng(seed)
    if n == 0:
        boxes = np.zeros((0, 7))
        pts = rng.normal(0, 5, (m, 3))
    else:
        pts, boxes = random_scene(rng, max(m, 2), n, spread=8)
        pts = pts[:m]
    check_against_ref(pts, boxes, margin=margin)


# ---------------------------------------------------------------- segment stats
def test_segment_stats_matches_numpy():
    rng = np.random.default_rng(2)
    pts, boxes = random_scene(rng, 3000, 40)
    boxes = np.concatenate([boxes, [[500, 500, 0, 1, 1, 1, 0]]])  # an empty box at the end
    boxes = np.concatenate([[[600, 600, 0, 1, 1, 1, 0]], boxes])  # and one at the start
    vals = rng.normal(size=len(pts))
    off, idx = points_in_boxes(pts, boxes)
    st_ = segment_stats(vals, off, idx)
    for j in range(len(boxes)):
        v = vals[idx[off[j]:off[j + 1]]]
        assert st_.count[j] == len(v)
        if len(v):
            np.testing.assert_allclose([st_.min[j], st_.max[j], st_.mean[j], st_.std[j]],
                                       [v.min(), v.max(), v.mean(), v.std()], atol=1e-12)
        else:
            assert (st_.min[j], st_.max[j], st_.mean[j], st_.std[j]) == (0, 0, 0, 0)
    assert st_.count[0] == 0 and st_.count[-1] == 0


def test_segment_stats_all_empty_and_no_boxes():
    s = segment_stats(np.arange(5.0), np.array([0, 0, 0]), np.zeros(0, np.int64))
    np.testing.assert_array_equal(s.count, [0, 0])
    np.testing.assert_array_equal(s.max, [0, 0])
    s = segment_stats(np.arange(5.0), np.array([0]), np.zeros(0, np.int64))
    assert s.mean.shape == (0,)


def test_segment_stats_hand_example():
    s = segment_stats(np.array([1.0, 2.0, 3.0, 10.0]), np.array([0, 2, 2, 4]),
                      np.array([0, 1, 2, 3]))
    np.testing.assert_array_equal(s.count, [2, 0, 2])
    np.testing.assert_allclose(s.mean, [1.5, 0, 6.5])
    np.testing.assert_allclose(s.max, [2, 0, 10])
    np.testing.assert_allclose(s.min, [1, 0, 3])
    np.testing.assert_allclose(s.std, [0.5, 0, 3.5])


def test_segment_stats_propagates_nan_like_numpy():
    vals = np.array([1.0, np.nan, 3.0, 4.0, 5.0])
    s = segment_stats(vals, np.array([0, 3, 5]), np.arange(5))
    np.testing.assert_array_equal(s.count, [3, 2])
    assert np.isnan([s.min[0], s.max[0], s.mean[0], s.std[0]]).all()
    np.testing.assert_allclose([s.min[1], s.max[1], s.mean[1], s.std[1]], [4, 5, 4.5, 0.5])


@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_inbox_point_stats_against_brute_force(dt):
    """Count and intensity statistics of the points inside each box, against a dense
    membership and numpy's reductions; points with a NaN / inf coordinate are in no box,
    those with a non-finite intensity are left out of the statistics and of the count."""
    rng = np.random.default_rng(7)
    pts, boxes = random_scene(rng, 4000, 50, dtype=dt)
    inten = rng.uniform(0, 255, len(pts)).astype(dt)
    inten[rng.choice(len(pts), 200, replace=False)] = np.nan
    inten[rng.choice(len(pts), 20, replace=False)] = np.inf
    pts[rng.choice(len(pts), 100, replace=False), rng.integers(0, 3)] = np.nan
    boxes = np.concatenate([boxes, [[500, 500, 0, 1, 1, 1, 0], [0, 0, 0, np.nan, 1, 1, 0]]])
    st_, n_usable = bg.inbox_point_stats(pts, inten, boxes)
    usable = np.isfinite(pts).all(axis=1) & np.isfinite(inten)
    assert n_usable == np.count_nonzero(usable)
    dense = ref_inside(pts, boxes) & usable[:, None]
    for j in range(len(boxes)):
        v = inten[dense[:, j]].astype(np.float64)
        assert st_.count[j] == len(v)
        if len(v):
            np.testing.assert_allclose([st_.min[j], st_.max[j], st_.mean[j], st_.std[j]],
                                       [v.min(), v.max(), v.mean(), v.std()], rtol=1e-12)
        else:
            assert (st_.min[j], st_.max[j], st_.mean[j], st_.std[j]) == (0, 0, 0, 0)
    assert st_.count[-2:].tolist() == [0, 0]
    # the caller's usable count is taken as given
    assert bg.inbox_point_stats(pts, inten, boxes, 123)[1] == 123


def test_box_table_matches_numpy_formulas():
    """The compiled box table: half sizes grown by the margin, the BEV half extents and
    which boxes are valid / gridable, as the numpy formulas give them."""
    rng = np.random.default_rng(3)
    b = np.column_stack([rng.uniform(-50, 50, (40, 3)), rng.uniform(0.1, 8, (40, 3)),
                         rng.uniform(-4, 4, 40)])
    b[0, 3] = 0.0
    b[1, 4] = -1.0
    b[2, 6] = np.nan
    b[3, 0] = np.inf
    b[4, 0] = 2e15
    b[5, 3:7] = 1.79e308, 1.79e308, 1.0, 0.5  # finite half extents, an infinite side
    b[6, 5] = 0.05   # with margin -0.1: a negative half height
    for margin in (0.0, 0.3, -0.1):
        valid, gridable, side, t = bg._box_table(b, margin)
        with np.errstate(over="ignore", invalid="ignore"):
            c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
            half = b[:, 3:6] / 2.0 + margin
            ex = np.abs(c) * half[:, 0] + np.abs(s) * half[:, 1]
            ey = np.abs(s) * half[:, 0] + np.abs(c) * half[:, 1]
            ref_side = 2.0 * np.maximum(ex, ey)
            ref_valid = (np.isfinite(b).all(axis=1) & (np.min(b[:, 3:6], axis=1) > 0.0)
                         & (np.min(half, axis=1) >= 0.0) & np.isfinite(half).all(axis=1))
            ref_grid = (ref_valid & np.isfinite(ref_side) & (np.abs(b[:, 0]) < 1e15)
                        & (np.abs(b[:, 1]) < 1e15))
        np.testing.assert_array_equal(valid, ref_valid)
        np.testing.assert_array_equal(gridable, ref_grid)
        ok = np.isfinite(ref_side)
        np.testing.assert_array_equal(side[ok], ref_side[ok])
        for got, ref in zip(t, (b[:, 0], b[:, 1], b[:, 2], c, s, half[:, 0], half[:, 1],
                                half[:, 2], ex, ey)):
            np.testing.assert_array_equal(got, ref)
        assert not valid[:4].any() and not gridable[4] and not gridable[5]
        assert valid[6] == (margin > -0.1)


@pytest.mark.parametrize("size", [1e-3, 1e-20, 1e-39])
def test_tiny_boxes(size):
    boxes = np.array([[0.0, 0.0, 0.0, size, size, size, 0.3], [1.0, 0, 0, size, size, size, 0]])
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [size, 0.0, 0.0], [0.5, 0.5, 0.0]])
    for dt in (np.float32, np.float64):
        off, idx = points_in_boxes(pts.astype(dt), boxes)
        np.testing.assert_array_equal(idx, [0, 1])
        np.testing.assert_array_equal(off, [0, 1, 2])
        # alone near the origin: the cell size must not underflow the points' dtype
        off, idx = points_in_boxes(pts.astype(dt), boxes[:1])
        np.testing.assert_array_equal(idx, [0])


@pytest.mark.parametrize("seed", range(3))
def test_float32_points_exactly_on_axis_aligned_faces(seed):
    # Box faces at float32-representable coordinates, points exactly on them: the float32
    # point -> cell mapping must never drop such a point (grid rounding slack).
    rng = np.random.default_rng(seed)
    n = 300
    lo = rng.uniform(-60, 60, (n, 2)).astype(np.float32).astype(np.float64)
    hi = lo + rng.uniform(0.5, 5, (n, 2)).astype(np.float32).astype(np.float64)
    hi = hi.astype(np.float32).astype(np.float64)
    boxes = np.column_stack([(lo + hi) / 2, np.zeros(n), hi - lo, np.ones(n), np.zeros(n)])
    t = rng.uniform(0, 1, (n, 1))
    along = (lo + t * (hi - lo)).astype(np.float32).astype(np.float64)
    faces = np.concatenate([
        np.column_stack([lo[:, 0], along[:, 1]]), np.column_stack([hi[:, 0], along[:, 1]]),
        np.column_stack([along[:, 0], lo[:, 1]]), np.column_stack([along[:, 0], hi[:, 1]])])
    pts = np.column_stack([faces, np.zeros(len(faces))]).astype(np.float32)
    got, ref = check_against_ref(pts, boxes)
    owner = np.tile(np.arange(n), 4)
    assert ref[np.arange(len(pts)), owner].all()  # every face point is in its own box
