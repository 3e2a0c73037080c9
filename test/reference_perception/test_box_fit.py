"""Tests of reference_perception.box_fit (oriented rectangle fits, vectorized over clusters)."""
import numpy as np
import pytest

from reference_perception.box_fit import (METHODS, fit_boxes, pca_yaw, rect_from_yaw,
                                          search_yaw, subsample, wrap_half_pi)


def outline(rng, cx, cy, l, w, yaw, n=120, sides=(0, 1, 2, 3), noise=0.01):
    """Points on the given sides of a rectangle (0: +x end, 1: +y side, 2: -x, 3: -y)."""
    t = np.linspace(-0.5, 0.5, n)                    # every side reaches its corners
    side = np.asarray(sides)[np.arange(n) % len(sides)]
    lx = np.select([side == 0, side == 2, side == 1, side == 3], [l / 2, -l / 2, t * l, t * l])
    ly = np.select([side == 1, side == 3, side == 0, side == 2], [w / 2, -w / 2, t * w, t * w])
    lx, ly = lx + rng.normal(0, noise, n), ly + rng.normal(0, noise, n)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.c_[cx + c * lx - s * ly, cy + s * lx + c * ly]


def angle_err(a, b):
    """Distance of rectangle orientations (period pi / 2: l / w are interchangeable)."""
    d = np.mod(np.asarray(a) - np.asarray(b), np.pi / 2)
    return np.minimum(d, np.pi / 2 - d)


@pytest.mark.parametrize("criterion", ["closeness", "variance"])
def test_l_shape_yaw_is_recovered(criterion):
    rng = np.random.default_rng(0)
    yaws = np.linspace(-1.5, 1.5, 9)
    pts = [outline(rng, 15 + 10 * k, -5, 4.4, 1.8, y, sides=(2, 3)) for k, y in enumerate(yaws)]
    xy = np.concatenate(pts)
    offsets = np.r_[0, np.cumsum([len(p) for p in pts])]
    got = search_yaw(xy, offsets, criterion)
    assert np.all(angle_err(got, yaws) < np.radians(3))
    cx, cy, l, w, yaw, edge = rect_from_yaw(xy, offsets, got)
    np.testing.assert_allclose(l, 4.4, atol=0.15)
    np.testing.assert_allclose(w, 1.8, atol=0.15)
    assert np.all(edge < 0.05)                      # every point on an edge


def test_area_and_pca_on_full_outlines():
    rng = np.random.default_rng(1)
    pts = [outline(rng, 0, 20, 6.0, 2.0, 0.4), outline(rng, -20, 0, 5.0, 1.0, -1.2)]
    xy = np.concatenate(pts)
    offsets = np.array([0, len(pts[0]), len(xy)])
    assert np.all(angle_err(search_yaw(xy, offsets, "area"), [0.4, -1.2]) < np.radians(3))
    assert np.all(angle_err(pca_yaw(xy, offsets), [0.4, -1.2]) < np.radians(5))


def test_rect_conventions():
    rng = np.random.default_rng(2)
    xy = outline(rng, 3.0, 4.0, 1.0, 3.0, 0.2, noise=0.0)   # longer along local y
    cx, cy, l, w, yaw, _ = rect_from_yaw(xy, np.array([0, len(xy)]), np.array([0.2]))
    assert l[0] >= w[0]
    assert l[0] == pytest.approx(3.0, abs=0.02) and w[0] == pytest.approx(1.0, abs=0.02)
    assert -np.pi / 2 <= yaw[0] < np.pi / 2
    assert angle_err(yaw[0], 0.2 + np.pi / 2) < 1e-9
    assert (cx[0], cy[0]) == (pytest.approx(3.0, abs=0.02), pytest.approx(4.0, abs=0.02))
    np.testing.assert_allclose(wrap_half_pi([np.pi / 2, -np.pi / 2, 0.1]), [-np.pi / 2] * 2 + [0.1])


def test_vectorized_equals_per_cluster():
    rng = np.random.default_rng(3)
    pts = [outline(rng, rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(0.5, 8),
                   rng.uniform(0.4, 2.5), rng.uniform(-3, 3), n=int(rng.integers(4, 150)),
                   sides=(0, 1) if k % 2 else (0, 1, 2, 3)) for k in range(12)]
    xyz = np.concatenate([np.c_[p, rng.uniform(-1.5, 0, len(p))] for p in pts])
    offsets = np.r_[0, np.cumsum([len(p) for p in pts])]
    gz = np.full(len(xyz), -1.7)
    boxes, cluster, method, edge = fit_boxes(xyz, gz, offsets)
    assert boxes.shape == (12 * len(METHODS), 7)
    np.testing.assert_array_equal(cluster, np.repeat(np.arange(12), len(METHODS)))
    for c in range(12):
        sl = slice(offsets[c], offsets[c + 1])
        one, _, _, e1 = fit_boxes(xyz[sl], gz[sl], np.array([0, offsets[c + 1] - offsets[c]]))
        np.testing.assert_allclose(boxes[cluster == c], one, atol=1e-9)
        np.testing.assert_allclose(edge[cluster == c], e1, atol=1e-9)


def test_heights_and_degenerate_clusters():
    # a vertical pole: all points at one (x, y); and a one-line cluster
    pole = np.c_[np.full(10, 5.0), np.full(10, 5.0), np.linspace(-1.5, 1.0, 10)]
    line = np.c_[np.linspace(10, 12, 10), np.full(10, 0.0), np.full(10, -1.0)]
    xyz = np.r_[pole, line]
    gz = np.full(20, -1.73)
    boxes, _, _, _ = fit_boxes(xyz, gz, np.array([0, 10, 20]))
    assert np.isfinite(boxes).all()
    assert np.all(boxes[:, 3:6] >= 0.1 - 1e-12)                 # valid boxes
    pole_boxes = boxes[:len(METHODS)]
    np.testing.assert_allclose(pole_boxes[:, 2] - pole_boxes[:, 5] / 2, -1.73)   # from ground
    np.testing.assert_allclose(pole_boxes[:, 2] + pole_boxes[:, 5] / 2, 1.0)     # to the top
    line_boxes = boxes[len(METHODS):]
    closeness = line_boxes[METHODS.index("closeness")]
    assert closeness[3] == pytest.approx(2.0, abs=1e-6)
    assert fit_boxes(np.zeros((0, 3)), np.zeros(0), np.array([0]))[0].shape == (0, 7)
    with pytest.raises(ValueError):
        fit_boxes(xyz, gz, np.array([0, 20]), methods=("nope",))


def test_subsample_is_bounded_and_spread():
    offsets = np.array([0, 3, 103, 1103])
    sel, new = subsample(offsets, 32)
    np.testing.assert_array_equal(np.diff(new), [3, 32, 32])
    assert np.all(np.diff(sel) > 0)
    assert sel[3] == 3 and sel[3 + 31] >= 90 and sel[-1] >= 1050   # spread over each group
