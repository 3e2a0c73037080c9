"""LidarMetaSeg segments: periodic 8-connected labelling, interior pixels and neighbourhood
class counts (compiled kernels) against a breadth-first search over pixel sets."""
import numpy as np
import pytest

from lidar_quality_core.lms.segments import interior_mask, label_periodic, neighbour_class_counts
from lms_images import NB8, components, neighbours


def reference_labels(img):
    """Labels by flood fill from each unlabelled pixel in raster order (ids in order of
    first pixel), the value of each component."""
    lab = np.full(img.shape, -1, dtype=np.int32)
    comps = components(img)
    for i, comp in enumerate(comps):
        for p in comp:
            lab[p] = i
    return lab, len(comps), np.array([img[min(c)] for c in comps], dtype=img.dtype)


def assert_labels_exact(img):
    lab, n, values = label_periodic(img, return_values=True)
    want_lab, want_n, want_values = reference_labels(img)
    assert lab.dtype == np.int32 and lab.shape == img.shape
    assert type(n) is int and n == want_n
    np.testing.assert_array_equal(lab, want_lab)
    assert values.dtype == img.dtype
    np.testing.assert_array_equal(values, want_values)
    lab2, n2 = label_periodic(img)
    np.testing.assert_array_equal(lab2, lab)
    assert n2 == n


def blobs(rng, R, C, k, cell=3):
    """Classes constant over cells of cell x cell pixels, shifted by a random column so
    that components cross the seam."""
    small = rng.integers(0, k, (-(-R // cell), -(-C // cell)))
    img = np.repeat(np.repeat(small, cell, 0), cell, 1)[:R, :C]
    return np.roll(img, int(rng.integers(0, C)), axis=1)


def adversarial_images():
    """Shapes that stress the union-find: merges found late, the seam, degenerate sizes."""
    out = []
    comb = np.zeros((12, 15), np.int32)
    comb[:, ::2] = 1
    out += [comb.copy()]
    comb[-1] = 1                          # teeth joined only by the last row
    out += [comb.copy()]
    comb = np.zeros((12, 15), np.int32)
    comb[::2] = 1
    comb[:, -1] = 1                       # rows joined across the seam only
    comb[:, 0] = 0
    out += [comb]
    spiral = np.zeros((11, 11), np.int32)
    r0, r1, c0, c1 = 0, 10, 0, 10
    while r0 <= r1 and c0 <= c1:
        spiral[r0, c0:c1 + 1] = spiral[r0:r1 + 1, c1] = 1
        spiral[r1, c0:c1 + 1] = 1
        spiral[r0 + 2:r1 + 1, c0] = 1
        r0, r1, c0, c1 = r0 + 2, r1 - 2, c0 + 2, c1 - 2
    out += [spiral]
    out += [(np.indices((9, 14)).sum(0) % 2).astype(np.int32)]       # checkerboard
    stair = np.zeros((8, 8), np.int64)
    stair[np.arange(8), np.arange(8)] = 1                            # diagonal chain
    stair[1::2, -1] = 2
    out += [stair]
    seam = np.zeros((6, 20), np.int32)
    seam[:, 3:17] = 1                     # class 0 only joined across the seam
    seam[::2, 0] = 2
    out += [seam]
    diag = np.zeros((4, 6), np.int32)
    diag[[0, 2], 0] = 1
    diag[[1, 3], -1] = 1                  # joined only by diagonals across the seam
    out += [diag]
    out += [np.zeros((5, 7), np.int32), np.full((5, 7), -1, np.int32),
            np.full((1, 1), 3, np.int32), np.zeros((2, 2), np.int32)]
    out += [np.array([[0, 1, 0, 1, 0]]), np.array([[0], [1], [0], [0], [-1], [0]]),
            np.array([[0, 1, 1], [1, 1, 0]]), np.array([[1, 0], [0, 1]])]
    return out


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


def test_label_periodic_exact_on_random_images():
    rng = np.random.default_rng(2)
    for i in range(150):
        R, C = int(rng.integers(1, 9)), int(rng.integers(1, 13))
        k = int(rng.choice([1, 2, 4, 9]))
        if i % 3 == 0:
            R, C = int(rng.integers(6, 20)), int(rng.integers(6, 40))
            img = blobs(rng, R, C, k)
        else:
            img = rng.integers(0, k, (R, C))
        if i % 2:
            img[rng.random((R, C)) < rng.choice([0.1, 0.5])] = -1
        assert_labels_exact(img.astype(np.int32 if i % 4 < 2 else np.int64))


def test_label_periodic_exact_on_adversarial_images():
    for img in adversarial_images():
        assert_labels_exact(img)
        assert_labels_exact(np.ascontiguousarray(img[:, ::-1]))
        assert_labels_exact(np.asfortranarray(img))


def test_label_periodic_other_dtypes():
    rng = np.random.default_rng(3)
    img = rng.integers(-1, 4, (6, 9))
    for dt in (np.int8, np.int16, np.uint8, np.uint32, np.bool_):
        assert_labels_exact(img.astype(dt))      # unsigned: no background
    big = np.where(img < 0, np.uint64(2 ** 63 + 1), img.astype(np.uint64))
    assert_labels_exact(big)
    lab, n, values = label_periodic(big, return_values=True)
    assert (lab >= 0).all() and np.uint64(2 ** 63 + 1) in values
    assert_labels_exact(img[:, ::2])             # not contiguous
    with pytest.raises(TypeError):
        label_periodic(img.astype(float))
    for shape in ((0, 4), (3, 0)):
        lab, n, values = label_periodic(np.zeros(shape, np.int32), return_values=True)
        assert lab.shape == shape and n == 0 and values.dtype == np.int32


def brute_interior(img):
    R, C = img.shape
    out = np.zeros((R, C), dtype=bool)
    for r in range(R):
        for c in range(C):
            # all 8 neighbours exist (rows do not wrap, columns do) and are equal
            out[r, c] = 0 < r < R - 1 and all(img[r + dr, (c + dc) % C] == img[r, c]
                                              for dr, dc in NB8)
    return out


def test_interior_mask_matches_neighbour_definition():
    rng = np.random.default_rng(1)
    for _ in range(30):
        R, C = rng.integers(1, 7), rng.integers(1, 10)
        img = rng.integers(0, 2, (R, C))
        np.testing.assert_array_equal(interior_mask(img), brute_interior(img))


def test_interior_mask_blobs_dtypes_and_adversarial():
    rng = np.random.default_rng(4)
    images = adversarial_images()
    for i in range(40):
        R, C = int(rng.integers(1, 16)), int(rng.integers(1, 30))
        img = blobs(rng, R, C, int(rng.choice([1, 2, 5])), cell=int(rng.integers(2, 5)))
        images.append(img.astype((np.int32, np.int64, np.int8, np.uint16)[i % 4]))
    for img in images:
        got = interior_mask(img)
        assert got.dtype == np.bool_ and got.shape == img.shape
        np.testing.assert_array_equal(got, brute_interior(img))


def brute_neighbour_counts(segments, Y, px, n_seg, n):
    R, C = segments.shape
    out = np.zeros((n_seg, n), dtype=np.int64)
    for p in px:
        r, c = divmod(int(p), C)
        others = {segments[q] for q in neighbours(r, c, R, C)} - {segments[r, c]}
        for s in others:
            if s >= 0:
                out[s, Y[r, c]] += 1
    return out


def test_neighbour_class_counts_matches_pixel_sets():
    rng = np.random.default_rng(5)
    images = adversarial_images()
    for i in range(60):
        R, C = int(rng.integers(1, 12)), int(rng.integers(1, 25))
        img = (blobs(rng, R, C, 4, cell=2) if i % 2 else rng.integers(0, 4, (R, C)))
        if i % 3 == 0:
            img[rng.random((R, C)) < 0.2] = -1
        images.append(img.astype(np.int32 if i % 2 else np.int64))
    for img in images:
        seg, n_seg = label_periodic(img)
        n = int(img.max()) + 1 if img.max() >= 0 else 1
        fg = np.flatnonzero(img.reshape(-1) >= 0)
        boundary = np.flatnonzero(~interior_mask(img) & (img >= 0))
        repeated = rng.permutation(np.concatenate([fg, fg[: len(fg) // 2]]))
        for px in (boundary, fg, repeated, fg[:0]):
            got = neighbour_class_counts(seg, img, px, n_seg, n)
            assert got.dtype == np.int64 and got.shape == (n_seg, n)
            np.testing.assert_array_equal(got, brute_neighbour_counts(seg, img, px, n_seg, n))


def test_neighbour_class_counts_bins_and_errors():
    img = np.array([[0, 1, 2], [0, 1, 2]], np.int32)
    seg, n_seg = label_periodic(img)
    px = np.arange(img.size)
    # a class outside 0..n-1 falls in the flat bin segment * n + class, if there is one
    # (the np.bincount the kernel replaced)
    got = neighbour_class_counts(seg, img, px, n_seg, 2)
    flat = np.zeros(n_seg * 2, np.int64)
    for p in px:
        r, c = divmod(int(p), 3)
        for s in {seg[q] for q in neighbours(r, c, 2, 3)} - {seg[r, c]}:
            if s * 2 + img[r, c] < n_seg * 2:
                flat[s * 2 + img[r, c]] += 1
    np.testing.assert_array_equal(got, flat.reshape(n_seg, 2))
    with pytest.raises(IndexError):
        neighbour_class_counts(seg, img, np.array([6]), n_seg, 3)
    with pytest.raises(IndexError):
        neighbour_class_counts(seg, img, np.array([-1]), n_seg, 3)
    # a background pixel (class -1) next to segment 0 has no bin
    bg = np.array([[0, -1]], np.int32)
    seg, n_seg = label_periodic(bg)
    with pytest.raises(ValueError):
        neighbour_class_counts(seg, bg, np.array([1]), n_seg, 1)
    with pytest.raises(ValueError):
        neighbour_class_counts(seg, img, px, n_seg, 3)      # shapes differ
