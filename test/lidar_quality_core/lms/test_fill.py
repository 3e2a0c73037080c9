import numpy as np
import pytest

from lidar_quality_core.lms.fill import fill_image, nearest_source


def brute_nearest(mask):
    """Nearest True pixel by exhaustive search with the documented ties: squared
    distance, then the row offset, then left before right, then the upper row."""
    R, C = mask.shape
    qr, qc = np.nonzero(mask)
    out = np.empty((R, C), dtype=np.int64)
    for r in range(R):
        for c in range(C):
            d_right = (qc - c) % C
            d_left = (c - qc) % C
            dc = np.minimum(d_left, d_right)
            side = (d_left > d_right).astype(int)     # 0: left (or same column)
            d2 = dc * dc + (qr - r) ** 2
            best = min(zip(d2, np.abs(qr - r), side, qr, qc))
            out[r, c] = best[3] * C + best[4]
    return out


@pytest.mark.parametrize("seed", range(8))
def test_matches_brute_force_with_ties(seed):
    rng = np.random.default_rng(seed)
    R, C = rng.integers(1, 7), rng.integers(1, 13)
    mask = rng.random((R, C)) < rng.choice([0.05, 0.3, 0.8])
    if not mask.any():
        mask[rng.integers(R), rng.integers(C)] = True
    np.testing.assert_array_equal(nearest_source(mask), brute_nearest(mask))


def test_projected_pixels_are_their_own_source_and_empty_mask():
    mask = np.zeros((3, 5), bool)
    assert (nearest_source(mask) == -1).all()
    mask[1, 2] = True
    src = nearest_source(mask)
    assert (src == 1 * 5 + 2).all()
    full = np.ones((2, 3), bool)
    np.testing.assert_array_equal(nearest_source(full).ravel(), np.arange(6))


def test_columns_wrap_around_rows_do_not():
    mask = np.zeros((3, 10), bool)
    mask[1, 0] = True
    mask[0, 5] = True
    src = nearest_source(mask)
    assert src[1, 9] == 1 * 10 + 0        # across the seam: 1 column away
    assert src[1, 8] == 1 * 10 + 0
    assert src[0, 4] == 0 * 10 + 5
    mask = np.zeros((5, 4), bool)
    mask[0, 1] = True
    mask[3, 1] = True
    # row 4 is 1 below row 3; rows do not wrap to row 0
    assert nearest_source(mask)[4, 1] == 3 * 4 + 1


def test_ties_prefer_the_same_row_then_left_then_up():
    mask = np.zeros((5, 9), bool)
    mask[1, 4] = True                       # (2, 4): one row up
    assert nearest_source(mask)[2, 4] == 1 * 9 + 4
    mask[2, 5] = True                       # the same distance in its own row wins
    assert nearest_source(mask)[2, 4] == 2 * 9 + 5
    mask[2, 3] = True                       # left over right
    assert nearest_source(mask)[2, 4] == 2 * 9 + 3
    mask = np.zeros((5, 9), bool)
    mask[0, 5] = mask[1, 2] = True          # (2, 4): d^2 = 5 both; row offset 1 wins
    assert nearest_source(mask)[2, 4] == 1 * 9 + 2
    mask = np.zeros((5, 9), bool)
    mask[1, 4] = mask[3, 4] = True          # up and down: up wins
    assert nearest_source(mask)[2, 4] == 1 * 9 + 4


def test_far_pixels_fall_back_to_the_exact_transform():
    rng = np.random.default_rng(3)
    mask = np.zeros((4, 64), bool)
    mask[rng.integers(0, 4, 3), rng.integers(0, 64, 3)] = True
    src = nearest_source(mask, max_offset=2)
    want = brute_nearest(mask)
    R, C = mask.shape

    def dist2(s):
        r, c = np.divmod(s, C)
        rr, cc = np.divmod(np.arange(R * C).reshape(R, C), C)
        dc = np.minimum((c - cc) % C, (cc - c) % C)
        return dc ** 2 + (r - rr) ** 2

    np.testing.assert_array_equal(dist2(src), dist2(want))   # same distance, ties aside
    assert mask.reshape(-1)[src].all()


def test_fill_image_carries_trailing_axes():
    mask = np.zeros((2, 4), bool)
    mask[0, 0] = True
    mask[1, 2] = True
    img = np.zeros((2, 4, 3))
    img[0, 0] = [1, 2, 3]
    img[1, 2] = [4, 5, 6]
    out = fill_image(img, mask)
    np.testing.assert_array_equal(out[0, 1], [1, 2, 3])
    np.testing.assert_array_equal(out[1, 3], [4, 5, 6])
    np.testing.assert_array_equal(out[0, 3], [1, 2, 3])   # across the seam


def numpy_nearest(mask, max_offset=64):
    """Plain numpy reference of :func:`nearest_source` (its implementation before the
    compiled kernel): a vertical scan, then a loop over column offsets for the unresolved
    pixels, the EDT for those past ``max_offset``."""
    from lidar_quality_core.lms.fill import _edt_periodic

    R, C = mask.shape
    if not mask.any():
        return np.full((R, C), -1, dtype=np.int64)
    far = 1 << 20
    rows = np.arange(R)[:, None]
    up = np.maximum.accumulate(np.where(mask, rows, -far), axis=0)
    dn = np.minimum.accumulate(np.where(mask, rows, 2 * far)[::-1], axis=0)[::-1]
    take_up = rows - up <= dn - rows
    g = np.minimum(np.where(take_up, rows - up, dn - rows), far).reshape(-1)
    srow = np.where(take_up, up, dn).reshape(-1)
    src = np.arange(R * C, dtype=np.int64)
    empty = np.flatnonzero(~mask.reshape(-1))
    er, ec = np.divmod(empty, C)
    best = g[empty] ** 2
    best_src = srow[empty] * C + ec
    active = np.arange(len(empty))
    dc, last = 1, min(C // 2, max_offset)
    while len(active) and dc <= last:
        active = active[best[active] >= dc * dc]
        r, c = er[active], ec[active]
        for cc in ((c + dc) % C, (c - dc) % C):          # right first: left wins ties
            pix = r * C + cc
            cand = dc * dc + g[pix] ** 2
            better = cand <= best[active]
            best[active[better]] = cand[better]
            best_src[active[better]] = srow[pix[better]] * C + cc[better]
        dc += 1
    if dc > max_offset and dc <= C // 2:
        left = active[best[active] >= dc * dc]
        best_src[left] = _edt_periodic(mask).reshape(-1)[empty[left]]
    src[empty] = best_src
    return src.reshape(R, C)


@pytest.mark.parametrize("shape", [(64, 512), (7, 33), (1, 9), (9, 1), (2, 2), (16, 130)])
def test_matches_the_numpy_reference(shape):
    """Every density from a single pixel (the EDT for most) to a full image, and offsets
    from none (all to the EDT) to beyond half the width."""
    rng = np.random.default_rng(sum(shape))
    R, C = shape
    for frac in (0.0, 1e-3, 0.01, 0.1, 0.5, 0.9, 1.0):
        mask = rng.random(shape) < frac
        if frac and not mask.any():
            mask[rng.integers(R), rng.integers(C)] = True
        for max_offset in (64, 3, 1, 0, -2, 10 ** 6):
            np.testing.assert_array_equal(nearest_source(mask, max_offset),
                                          numpy_nearest(mask, max_offset),
                                          err_msg=f"{shape} {frac} {max_offset}")
    stripes = np.zeros(shape, bool)
    stripes[:, ::max(1, C // 3)] = True
    np.testing.assert_array_equal(nearest_source(stripes[:, ::-1], 1),
                                  numpy_nearest(stripes[:, ::-1], 1))


def test_projected_frame_matches_the_numpy_reference():
    """A simulated scan's mask (dense, gaps along rows and columns), with and without
    dropped rows."""
    from lidar_sim.frames import split_frames
    from lidar_sim.sensor import hdl64

    from lidar_quality_core.lms.projection import RangeImageConfig, project

    f = next(split_frames("reference_test", sequences=[0], frames=30))
    s = hdl64()
    mask = project(f.xyz, RangeImageConfig.from_elevations(s.elevations_deg, s.columns),
                   ring=f.ring).mask
    for m in (mask, mask & (np.arange(len(mask))[:, None] % 5 != 0)):
        np.testing.assert_array_equal(nearest_source(m), numpy_nearest(m))
