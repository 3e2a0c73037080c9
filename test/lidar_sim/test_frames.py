import numpy as np
import pytest

from lidar_sim.frames import _ARRAY_FIELDS, sequence_frames, split_frames
from lidar_sim.splits import SPLITS, Split, split


def test_splits_are_disjoint_by_seed():
    seeds = {s.sequence_seed(i) for s in SPLITS.values() for i in range(s.sequences)}
    assert len(seeds) == sum(s.sequences for s in SPLITS.values())
    with pytest.raises(KeyError, match="known"):
        split("nope")
    with pytest.raises(IndexError):
        SPLITS["demo"].sequence_seed(1)


def test_cache_round_trips_frames(tmp_path):
    sp = Split("tiny", seed=55, sequences=1, frames=2)
    fresh = list(split_frames(sp, cache_dir=tmp_path))
    assert len(list(tmp_path.rglob("*.npz"))) == 2
    cached = list(split_frames(sp, cache_dir=tmp_path))
    direct = list(sequence_frames(55000, 2))
    for a, b, c in zip(fresh, cached, direct):
        assert ((a.sequence, a.index, a.stamp_ns, a.gt_kitti_type)
                == (b.sequence, b.index, b.stamp_ns, b.gt_kitti_type))
        for k in _ARRAY_FIELDS:
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
            np.testing.assert_array_equal(getattr(a, k), getattr(c, k))
    assert fresh[0].xyz.shape[0] > 50_000


def test_simulator_modules_exist():
    from pathlib import Path

    import lidar_sim.frames as fr

    here = Path(fr.__file__).parent
    assert all((here / f"{m}.py").is_file() for m in fr.SIMULATOR_MODULES)
