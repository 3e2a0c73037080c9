"""LidarMetaSeg segments: periodic 8-connected labelling and interior pixels against a
breadth-first search over pixel sets."""
import numpy as np

from lidar_quality_core.lms.segments import interior_mask, label_periodic
from lms_images import NB8, components


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


def test_interior_mask_matches_neighbour_definition():
    rng = np.random.default_rng(1)
    for _ in range(30):
        R, C = rng.integers(1, 7), rng.integers(1, 10)
        img = rng.integers(0, 2, (R, C))
        got = interior_mask(img)
        for r in range(R):
            for c in range(C):
                # all 8 neighbours exist (rows do not wrap, columns do) and are equal
                want = 0 < r < R - 1 and all(img[r + dr, (c + dc) % C] == img[r, c]
                                             for dr, dc in NB8)
                assert got[r, c] == want, (r, c)
