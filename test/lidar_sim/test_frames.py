import numpy as np
import pytest

from lidar_sim import classes as C
from lidar_sim.frames import _ARRAY_FIELDS, sequence_frames, split_frames
from lidar_sim.scene import SCENE_TYPES, SceneConfig
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


def _assert_frames_equal(a, b):
    assert ((a.sequence, a.index, a.stamp_ns, a.gt_kitti_type)
            == (b.sequence, b.index, b.stamp_ns, b.gt_kitti_type))
    for k in _ARRAY_FIELDS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_scene_argument_defaults_to_the_street():
    # the default street by name or config is the frames the splits hold, bit for bit
    default = list(sequence_frames(55000, 2, sequence=3))
    for scene in ("street", SceneConfig(), SCENE_TYPES["street"]):
        for a, b in zip(default, sequence_frames(55000, 2, sequence=3, scene=scene)):
            _assert_frames_equal(a, b)
    with pytest.raises(KeyError, match="known"):
        next(sequence_frames(55000, 1, scene="nope"))


def test_suburban_frames_fewer_buildings_more_vegetation():
    frac = {}
    for scene in ("street", "suburban"):
        frames = [next(sequence_frames(seed, 1, scene=scene)) for seed in range(3)]
        frac[scene] = np.array([[np.mean(f.semantic == c) for c in (C.BUILDING, C.VEGETATION)]
                                for f in frames])
        if scene == "suburban":
            for f in frames:   # detections to score: parked / moving cars near the sensor
                near = np.hypot(f.gt_boxes[:, 0], f.gt_boxes[:, 1]) <= 40
                assert ((f.gt_class == C.CAR) & near & (f.gt_num_points >= 10)).sum() >= 5
    street, sub = frac["street"], frac["suburban"]
    # measured building 24/25/22 % vs 6/5/6 %, vegetation 0.5/0.1/0.4 % vs 9/15/13 %
    assert np.all(sub[:, 0] < 0.8 * street[:, 0]) and sub[:, 0].sum() < 0.5 * street[:, 0].sum()
    assert np.all(sub[:, 1] > 0.04) and np.all(sub[:, 1] > 5 * street[:, 1])
