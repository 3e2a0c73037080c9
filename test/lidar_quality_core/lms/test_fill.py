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
