"""Tests for lidar_sim.classes (the class table)."""
import numpy as np
import pytest

from lidar_sim import classes as C

EXPECTED_SK = {
    "unlabeled": 0, "road": 40, "sidewalk": 48, "terrain": 72, "building": 50, "fence": 51,
    "vegetation": 70, "trunk": 71, "pole": 80, "traffic-sign": 81, "car": 10, "truck": 18,
    "pedestrian": 30, "cyclist": 31,
}


def test_ids_contiguous_unique_and_names():
    ids = [c.id for c in C.CLASSES]
    assert ids == list(range(C.NUM_CLASSES))
    assert len(set(C.CLASS_NAMES)) == C.NUM_CLASSES
    assert C.CLASSES[0].name == "unlabeled" and C.UNLABELED == 0
    assert set(C.CLASS_NAMES) == set(EXPECTED_SK)


def test_semantickitti_ids_exact():
    for c in C.CLASSES:
        assert c.semantickitti_id == EXPECTED_SK[c.name]
        assert C.SEMANTICKITTI_LABELS[c.semantickitti_id]  # a real SemanticKITTI label
    sk = [c.semantickitti_id for c in C.CLASSES]
    assert len(set(sk)) == len(sk)


def test_round_trips():
    for c in C.CLASSES:
        assert C.class_id(c.name) == c.id
        assert C.class_name(c.id) == c.name
    ids = np.arange(C.NUM_CLASSES)
    sk = C.to_semantickitti(ids)
    assert sk.dtype == np.uint32
    assert np.array_equal(C.from_semantickitti(sk), ids)
    # full .label values carry the instance in the upper 16 bits
    labels = sk | (np.arange(C.NUM_CLASSES, dtype=np.uint32) << 16)
    assert np.array_equal(C.from_semantickitti(labels), ids)
    with pytest.raises(KeyError):
        C.class_id("bus")


def test_extra_semantickitti_ids_map_sensibly():
    assert C.from_semantickitti([252, 254, 253, 258, 60, 1, 99, 1000]).tolist() == [
        C.CAR, C.PEDESTRIAN, C.CYCLIST, C.TRUCK, C.ROAD, 0, 0, 0]


def test_things():
    assert sorted(C.THING_CLASS_IDS.tolist()) == sorted(
        [C.CAR, C.TRUCK, C.PEDESTRIAN, C.CYCLIST])
    assert set(C.THING_CLASS_IDS.tolist()) | set(C.STUFF_CLASS_IDS.tolist()) == set(
        range(C.NUM_CLASSES))
    kitti = {C.class_name(i): C.kitti_type(i) for i in C.THING_CLASS_IDS}
    assert kitti == {"car": "Car", "truck": "Truck", "pedestrian": "Pedestrian",
                     "cyclist": "Cyclist"}
    assert all(C.kitti_type(i) is None for i in C.STUFF_CLASS_IDS)
    assert C.is_thing(C.CAR) is True and C.is_thing(C.ROAD) is False
    assert C.is_thing(np.array([C.CAR, C.ROAD])).tolist() == [True, False]


def test_colors_and_reflectivity():
    col = C.colors_rgb()
    assert col.shape == (C.NUM_CLASSES, 3) and col.dtype == np.uint8
    # RGB is SemanticKITTI's BGR reversed
    assert tuple(col[C.CAR]) == tuple(reversed(C.SEMANTICKITTI_COLORS_BGR[10]))
    assert np.all((C.colors_rgb(True) >= 0) & (C.colors_rgb(True) <= 1))
    for c in C.CLASSES:
        lo, hi = c.reflectivity
        assert 0 <= lo <= hi <= 1
    for lo, hi in C.MATERIAL_REFLECTIVITY.values():
        assert 0 <= lo <= hi <= 1
    assert C.CLASSES[C.ROAD].reflectivity[1] <= 0.25          # dark asphalt
    assert C.CLASSES[C.TRAFFIC_SIGN].reflectivity[0] >= 0.8   # retroreflective
    rng = np.random.default_rng(0)
    r = C.sample_reflectivity(rng, C.CAR, 100)
    assert r.shape == (100,) and r.min() >= 0.1 and r.max() <= 0.8
    assert 0.55 <= C.sample_reflectivity(rng, material="lane_paint") <= 0.75


def test_class_map_structure(tmp_path):
    m = C.semantickitti_class_map()
    for key in ("labels", "color_map", "learning_map", "learning_map_inv", "learning_ignore"):
        assert key in m
    assert set(m["labels"]) == set(m["color_map"]) == set(m["learning_map"])
    assert all(len(v) == 3 for v in m["color_map"].values())
    inv = m["learning_map_inv"]
    assert sorted(inv) == list(range(C.NUM_CLASSES))
    for ours, sk in inv.items():
        assert m["learning_map"][sk] == ours       # inverse on our classes
    assert set(m["learning_map"].values()) <= set(inv)
    assert m["learning_ignore"][0] is True and not any(
        v for k, v in m["learning_ignore"].items() if k)
    path = tmp_path / "lidar_sim.yaml"
    C.semantickitti_class_map(path)
    yaml = pytest.importorskip("yaml")
    loaded = yaml.safe_load(path.read_text())
    assert loaded["learning_map_inv"] == inv
    assert loaded["color_map"][10] == list(C.SEMANTICKITTI_COLORS_BGR[10])
