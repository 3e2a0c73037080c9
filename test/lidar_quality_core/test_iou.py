"""Tests for lidar_quality_core.iou (rotated BEV / 3D IoU)."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lidar_quality_core import iou as iou_mod
from lidar_quality_core.iou import (bev_intersection_area, iou_3d, iou_3d_pairs, iou_bev,
                                    iou_bev_indexed, iou_bev_pairs, sparse_iou)

OCT = 2.0 * (math.sqrt(2.0) - 1.0)  # unit square & its 45-degree rotation: octagon area


# ---------------------------------------------------------------- independent reference
def ref_poly(box):
    x, y, _, l, w, _, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    return [(x + c * u - s * v, y + s * u + c * v)
            for u, v in ((l / 2, w / 2), (-l / 2, w / 2), (-l / 2, -w / 2), (l / 2, -w / 2))]


def ref_clip(subject, clip):
    """Plain-Python Sutherland-Hodgman of a polygon by a CCW convex polygon."""
    out = subject
    for i in range(len(clip)):
        (ax, ay), (bx, by) = clip[i], clip[(i + 1) % len(clip)]
        side = [(bx - ax) * (py - ay) - (by - ay) * (px - ax) for px, py in out]
        new = []
        for k in range(len(out)):
            p, q = out[k], out[(k + 1) % len(out)]
            sp, sq = side[k], side[(k + 1) % len(out)]
            if sp >= 0:
                new.append(p)
            if (sp > 0 > sq) or (sp < 0 < sq):
                t = sp / (sp - sq)
                new.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        out = new
        if not out:
            break
    return out


def ref_area(poly):
    return 0.5 * sum(poly[k][0] * poly[(k + 1) % len(poly)][1]
                     - poly[k][1] * poly[(k + 1) % len(poly)][0] for k in range(len(poly)))


def ref_iou(a, b, three_d=False):
    poly = ref_clip(ref_poly(a), ref_poly(b))
    inter = abs(ref_area(poly)) if len(poly) >= 3 else 0.0
    ua, ub = a[3] * a[4], b[3] * b[4]
    if three_d:
        zo = max(0.0, min(a[2] + a[5] / 2, b[2] + b[5] / 2) - max(a[2] - a[5] / 2, b[2] - b[5] / 2))
        inter, ua, ub = inter * zo, ua * a[5], ub * b[5]
    return inter / (ua + ub - inter)


def rand_boxes(rng, n, spread=4.0):
    return np.column_stack([rng.uniform(-spread, spread, (n, 2)), rng.uniform(-1, 1, n),
                            rng.uniform(0.2, 5, n), rng.uniform(0.2, 3, n),
                            rng.uniform(0.3, 3, n), rng.uniform(-4, 4, n)])


def box(x=0.0, y=0.0, z=0.0, l=1.0, w=1.0, h=1.0, yaw=0.0):
    return np.array([[x, y, z, l, w, h, yaw]], dtype=np.float64)


# ---------------------------------------------------------------- hand-computed cases
def test_identical_boxes_iou_one():
    rng = np.random.default_rng(0)
    b = rand_boxes(rng, 40)
    np.testing.assert_allclose(np.diag(iou_bev(b, b)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.diag(iou_3d(b, b)), 1.0, atol=1e-9)
    np.testing.assert_allclose(iou_bev_pairs(b, b), 1.0, atol=1e-9)
    far = b + [1e6, -2e6, 0, 0, 0, 0, 0]  # precision far from the origin
    np.testing.assert_allclose(iou_bev_pairs(far, far), 1.0, atol=1e-9)


def test_rotated_45_square_octagon():
    expected = OCT / (2.0 - OCT)
    assert iou_bev(box(), box(yaw=np.pi / 4))[0, 0] == pytest.approx(expected, abs=1e-12)
    assert iou_bev(box(yaw=np.pi / 4), box())[0, 0] == pytest.approx(expected, abs=1e-12)
    assert bev_intersection_area(box(), box(yaw=np.pi / 4))[0, 0] == pytest.approx(OCT, 1e-12)
    # same about an arbitrary centre and with a common extra rotation
    a, b = box(3.0, -7.0, yaw=0.3), box(3.0, -7.0, yaw=0.3 + np.pi / 4)
    assert iou_bev(a, b)[0, 0] == pytest.approx(expected, abs=1e-12)


def test_half_shift_one_third_and_containment():
    assert iou_bev(box(), box(x=0.5))[0, 0] == pytest.approx(1 / 3, abs=1e-15)
    assert iou_bev(box(), box(y=-0.5))[0, 0] == pytest.approx(1 / 3, abs=1e-15)
    # containment: small / large area, whatever the rotation of the small box
    big = box(l=4, w=3, yaw=0.2)
    for yaw in (0.0, 0.7, 2.0):
        small = box(x=0.3, y=0.1, l=1.0, w=0.5, yaw=yaw)
        assert iou_bev(small, big)[0, 0] == pytest.approx(0.5 / 12, abs=1e-12)
        assert bev_intersection_area(big, small)[0, 0] == pytest.approx(0.5, abs=1e-12)


def test_3d_partial_z_overlap_by_hand():
    a = box(h=2.0)                      # z in [-1, 1]
    b = box(x=0.5, z=0.5, h=1.0)        # z in [0, 1], BEV overlap 0.5
    inter = 0.5 * 1.0
    assert iou_3d(a, b)[0, 0] == pytest.approx(inter / (2.0 + 1.0 - inter), abs=1e-15)
    assert iou_bev(a, b)[0, 0] == pytest.approx(1 / 3, abs=1e-15)
    # z-disjoint: 3D IoU 0 while BEV IoU is not
    c = box(z=5.0)
    assert iou_3d(a, c)[0, 0] == 0.0 and iou_bev(a, c)[0, 0] == 1.0
    # z-touching: 0
    assert iou_3d(box(h=2.0), box(z=1.5, h=1.0))[0, 0] == 0.0


def test_disjoint_and_touching():
    assert iou_bev(box(), box(x=3.0))[0, 0] == 0.0
    assert iou_bev(box(), box(x=1.0))[0, 0] == 0.0          # shared edge
    assert iou_bev(box(), box(x=1.0, y=1.0))[0, 0] == 0.0   # shared corner
    # rotated diamond touching the square at a vertex
    d = box(x=0.5 + math.sqrt(0.5), yaw=np.pi / 4)
    assert iou_bev(box(), d)[0, 0] == pytest.approx(0.0, abs=1e-9)
    # circles meet but the rectangles do not
    assert iou_bev(box(l=4, w=0.2), box(x=1.8, y=1.0, l=4, w=0.2, yaw=0.4))[0, 0] == 0.0


def test_collinear_edges():
    # same y extent, x overlap [0.5, 1] of [0, 1] and [0.5, 2.5]
    a, b = box(x=0.5), box(x=1.5, l=2.0)
    assert iou_bev(a, b)[0, 0] == pytest.approx(0.5 / (1 + 2 - 0.5), abs=1e-15)
    # partially shared collinear edge (rotated frame)
    a, b = box(l=2, w=1, yaw=0.6), box(l=2, w=1, yaw=0.6)
    b[0, :2] += 0.7 * np.array([math.cos(0.6), math.sin(0.6)])
    assert iou_bev(a, b)[0, 0] == pytest.approx(1.3 / 2.7, abs=1e-12)


def test_yaw_plus_pi_same_iou():
    rng = np.random.default_rng(3)
    a, b = rand_boxes(rng, 30), rand_boxes(rng, 40)
    flipped = b.copy()
    flipped[:, 6] += np.pi
    np.testing.assert_allclose(iou_bev(a, b), iou_bev(a, flipped), atol=1e-9)
    np.testing.assert_allclose(iou_3d(a, b), iou_3d(a, flipped), atol=1e-9)
    swapped = b.copy()  # l <-> w with a quarter turn is the same rectangle
    swapped[:, 3], swapped[:, 4] = b[:, 4], b[:, 3]
    swapped[:, 6] += np.pi / 2
    np.testing.assert_allclose(iou_bev(a, b), iou_bev(a, swapped), atol=1e-9)


def test_degenerate_boxes_give_zero_not_nan():
    good = box()
    bad = np.array([
        [0, 0, 0, 0, 1, 1, 0],         # zero length
        [0, 0, 0, 1, 0, 1, 0],         # zero width
        [0, 0, 0, -1, 1, 1, 0],        # negative
        [np.nan, 0, 0, 1, 1, 1, 0],
        [0, 0, 0, 1, 1, 1, np.inf],
        [0, 0, 0, np.inf, 1, 1, 0],
    ], dtype=float)
    for fn in (iou_bev, iou_3d, bev_intersection_area):
        m = fn(np.concatenate([good, bad]), np.concatenate([good, bad]))
        assert np.isfinite(m).all()
        assert m[0, 0] > 0
        np.testing.assert_array_equal(m[1:], 0.0)
        np.testing.assert_array_equal(m[:, 1:], 0.0)
    # zero height: BEV fine, 3D zero
    flat = box(h=0.0)
    assert iou_bev(flat, good)[0, 0] == 1.0
    assert iou_3d(flat, good)[0, 0] == 0.0
    assert iou_3d_pairs(flat, flat)[0] == 0.0


def test_empty_and_shapes():
    assert iou_bev(np.zeros((0, 7)), box()).shape == (0, 1)
    assert iou_3d(box(), np.zeros((0, 7))).shape == (1, 0)
    assert iou_bev_pairs(np.zeros((0, 7)), np.zeros((0, 7))).shape == (0,)
    with pytest.raises(ValueError):
        iou_bev_pairs(box(), np.zeros((2, 7)))
    with pytest.raises(ValueError):
        sparse_iou(box(), mode="2d")
    assert iou_bev(box().astype(np.float32), box())[0, 0] == 1.0


# ---------------------------------------------------------------- against the reference
@pytest.mark.parametrize("seed", range(4))
def test_matches_independent_clipping_reference(seed):
    rng = np.random.default_rng(seed)
    a, b = rand_boxes(rng, 25), rand_boxes(rng, 35)
    got_bev, got_3d = iou_bev(a, b), iou_3d(a, b)
    ref_bev = np.array([[ref_iou(x, y) for y in b] for x in a])
    ref_3d = np.array([[ref_iou(x, y, True) for y in b] for x in a])
    assert (ref_bev > 0).sum() > 50
    np.testing.assert_allclose(got_bev, ref_bev, atol=1e-9)
    np.testing.assert_allclose(got_3d, ref_3d, atol=1e-9)
    area = bev_intersection_area(a, b)
    np.testing.assert_allclose(area, ref_bev * (a[:, None, 3] * a[:, None, 4] + b[:, 3] * b[:, 4])
                               / (1 + ref_bev), atol=1e-9)


def test_monte_carlo_area():
    rng = np.random.default_rng(1)
    a, b = box(l=3, w=1.2, yaw=0.4), box(x=0.8, y=0.3, l=2, w=2.5, yaw=-1.1)
    pts = rng.uniform(-3, 3, (400_000, 2))

    def inside(p, bx):
        x, y, _, l, w, _, yaw = bx[0]
        c, s = math.cos(yaw), math.sin(yaw)
        u = c * (p[:, 0] - x) + s * (p[:, 1] - y)
        v = -s * (p[:, 0] - x) + c * (p[:, 1] - y)
        return (np.abs(u) <= l / 2) & (np.abs(v) <= w / 2)

    mc = 36.0 * np.mean(inside(pts, a) & inside(pts, b))
    got = bev_intersection_area(a, b)[0, 0]
    assert got == pytest.approx(mc, abs=4 * 36 * math.sqrt(mc / 36 / len(pts)) + 1e-3)


def test_kdtree_prefilter_path_agrees(monkeypatch):
    rng = np.random.default_rng(8)
    a, b = rand_boxes(rng, 60, spread=15), rand_boxes(rng, 70, spread=15)
    dense_ab, dense_aa = iou_bev(a, b), sparse_iou(a, None, "3d")
    monkeypatch.setattr(iou_mod, "_DENSE_PREFILTER_MAX", 0)
    np.testing.assert_array_equal(iou_bev(a, b), dense_ab)
    kd = sparse_iou(a, None, "3d")
    for x, y in zip(kd, dense_aa):
        np.testing.assert_array_equal(x, y)
    assert len(kd[0]) > 20 and np.all(kd[0] < kd[1])


def test_sparse_self_pairs_cover_upper_triangle():
    rng = np.random.default_rng(2)
    a = rand_boxes(rng, 50)
    i, j, v = sparse_iou(a)
    dense = np.zeros((50, 50))
    dense[i, j] = v
    full = iou_bev(a, a)
    np.testing.assert_allclose(dense, np.triu(full, 1), atol=1e-12)
    assert np.all(np.diff(i) >= 0)  # row-major


def test_pairs_equal_diagonal():
    rng = np.random.default_rng(4)
    a, b = rand_boxes(rng, 30), rand_boxes(rng, 30)
    np.testing.assert_allclose(iou_bev_pairs(a, b), np.diag(iou_bev(a, b)), atol=1e-12)
    np.testing.assert_allclose(iou_3d_pairs(a, b), np.diag(iou_3d(a, b)), atol=1e-12)


def test_indexed_pairs_equal_gathered_pairs_to_the_bit():
    rng = np.random.default_rng(9)
    a = rand_boxes(rng, 40)
    a[5:10] = a[:5] + [0.2, 0, 0, 0, 0, 0, 1e-9]   # near copies
    a[10:13] = a[10:13] * [1, 1, 1, 1, 1, 1, 0] + [0, 0, 0, 0, 0, 0, np.pi]
    i, j = np.triu_indices(40, 1)
    want = iou_bev_pairs(a[i], a[j])
    got = iou_bev_indexed(np.ascontiguousarray(a), i, j, np.cos(a[:, 6]), np.sin(a[:, 6]))
    np.testing.assert_array_equal(got.view(np.uint64), want.view(np.uint64))
    assert (want > 0).sum() > 20


def test_read_only_boxes_give_the_same_bits():
    # boxes a caller froze, or a view of a message's bytes, are read-only
    rng = np.random.default_rng(11)
    a, b = rand_boxes(rng, 25), rand_boxes(rng, 25)
    ra, rb = a.copy(), b.copy()
    ra.flags.writeable = rb.flags.writeable = False
    for f in (iou_bev, iou_3d, iou_bev_pairs, iou_3d_pairs, bev_intersection_area):
        np.testing.assert_array_equal(f(ra, rb).view(np.uint64), f(a, b).view(np.uint64))
    for x, y in zip(sparse_iou(ra), sparse_iou(a)):
        np.testing.assert_array_equal(x, y)
    i, j = np.triu_indices(25, 1)
    np.testing.assert_array_equal(
        iou_bev_indexed(ra, i, j, np.cos(a[:, 6]), np.sin(a[:, 6])).view(np.uint64),
        iou_bev_pairs(a[i], a[j]).view(np.uint64))


# ---------------------------------------------------------------- properties
box_st = st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-1, 1), st.floats(0.05, 5),
                   st.floats(0.05, 5), st.floats(0.05, 3), st.floats(-7, 7))


@settings(max_examples=150, deadline=None)
@given(a=st.lists(box_st, min_size=1, max_size=6), b=st.lists(box_st, min_size=1, max_size=6),
       theta=st.floats(-10, 10), tx=st.floats(-1e5, 1e5), ty=st.floats(-1e5, 1e5),
       tz=st.floats(-100, 100))
def test_iou_properties(a, b, theta, tx, ty, tz):
    a, b = np.array(a), np.array(b)
    m_bev, m_3d = iou_bev(a, b), iou_3d(a, b)
    for m, fn in ((m_bev, iou_bev), (m_3d, iou_3d)):
        assert np.isfinite(m).all() and (m >= 0).all() and (m <= 1).all()
        np.testing.assert_allclose(fn(b, a), m.T, atol=1e-9)  # symmetry

    def move(x):
        c, s = math.cos(theta), math.sin(theta)
        y = x.copy()
        y[:, 0] = c * x[:, 0] - s * x[:, 1] + tx
        y[:, 1] = s * x[:, 0] + c * x[:, 1] + ty
        y[:, 2] += tz
        y[:, 6] += theta
        return y

    np.testing.assert_allclose(iou_bev(move(a), move(b)), m_bev, atol=1e-7)
    np.testing.assert_allclose(iou_3d(move(a), move(b)), m_3d, atol=1e-7)
    ref = np.array([[ref_iou(x, y) for y in b] for x in a])
    np.testing.assert_allclose(m_bev, ref, atol=1e-9)
