"""Tests for lidar_sim.scene (procedural street scenes)."""
import dataclasses

import numpy as np
import pytest

from lidar_quality_core.box_geometry import corners_3d
from lidar_quality_core.iou import bev_intersection_area
from lidar_sim import classes as C
from lidar_sim.primitives import Primitives
from lidar_sim.scene import (EGO_SIZE, SCENE_TYPES, SIZE_RANGES, Scene, SceneConfig,
                             generate_scene, scene_config, street_cross_section)

SEEDS = range(6)


@pytest.fixture(scope="module", params=list(SCENE_TYPES))
def scenes(request):
    """Scenes of each scene type (the default "street" first): the generic checks below
    hold for every type."""
    return [generate_scene(s, SCENE_TYPES[request.param]) for s in SEEDS]


@pytest.fixture(scope="module")
def street():
    return [generate_scene(s) for s in SEEDS]


@pytest.fixture(scope="module")
def suburban():
    return [generate_scene(s, SCENE_TYPES["suburban"]) for s in SEEDS]


def _prims_equal(a: Primitives, b: Primitives) -> bool:
    for f in dataclasses.fields(Primitives):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if x.dtype != y.dtype or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


def _things_equal(a: Scene, b: Scene) -> bool:
    ta, tb = a.things, b.things
    return all(np.array_equal(getattr(ta, f.name), getattr(tb, f.name))
               if isinstance(getattr(ta, f.name), np.ndarray)
               else getattr(ta, f.name) == getattr(tb, f.name)
               for f in dataclasses.fields(ta))


def test_determinism():
    a, b, c = generate_scene(7), generate_scene(7), generate_scene(8)
    assert _prims_equal(a.static, b.static) and _things_equal(a, b)
    assert a.lanes == b.lanes
    assert not _prims_equal(a.static, c.static)
    assert not _things_equal(a, c)


def test_primitive_arrays_well_formed(scenes):
    for sc in scenes:
        p = sc.static
        assert p.ground_z == 0.0
        for kind, cols in (("box", 7), ("cylinder", 5), ("ellipsoid", 6)):
            arr = getattr(p, {"box": "boxes"}.get(kind, kind + "s"))
            n = len(arr)
            assert arr.shape == (n, cols) and arr.dtype == np.float64
            assert getattr(p, kind + "_class").shape == (n,)
            assert getattr(p, kind + "_class").dtype == np.int32
            assert getattr(p, kind + "_instance").dtype == np.int32
            assert np.all(getattr(p, kind + "_instance") == 0)   # stuff has no instance
            refl = getattr(p, kind + "_reflectivity")
            assert refl.shape == (n,) and np.all((refl >= 0) & (refl <= 1))
        assert set(np.unique(p.box_class)) <= {C.BUILDING, C.FENCE, C.POLE, C.TRAFFIC_SIGN}
        assert set(np.unique(p.cylinder_class)) == {C.POLE, C.TRUNK}
        assert set(np.unique(p.ellipsoid_class)) == {C.VEGETATION}
        assert np.all((p.ellipsoid_porosity >= 0) & (p.ellipsoid_porosity < 1))
        assert np.all(p.boxes[:, 3:6] > 0) and np.all(p.ellipsoids[:, 3:6] > 0)
        assert np.all(p.cylinders[:, 3] > p.cylinders[:, 2]) and np.all(p.cylinders[:, 4] > 0)
        # every stuff class is present
        for cls in (C.BUILDING, C.TRAFFIC_SIGN, C.POLE):
            assert np.any(p.box_class == cls)
        refl = sc.things.part_reflectivity
        assert np.all((refl >= 0) & (refl <= 1))


def test_ground_regions_tile_without_overlap(scenes):
    for sc in scenes[:2]:
        p = sc.static
        g = p.ground_regions
        assert np.all(g[:, 1] > g[:, 0]) and np.all(g[:, 3] > g[:, 2])
        ox = np.minimum(g[:, None, 1], g[None, :, 1]) - np.maximum(g[:, None, 0], g[None, :, 0])
        oy = np.minimum(g[:, None, 3], g[None, :, 3]) - np.maximum(g[:, None, 2], g[None, :, 2])
        inter = np.clip(ox, 0, None) * np.clip(oy, 0, None)
        np.fill_diagonal(inter, 0)
        assert inter.max() < 1e-9
        cs = street_cross_section(sc.config)
        # the street cross-section at x = ego is covered: road, sidewalk, terrain in order
        for y, cls in ((0.05, C.ROAD), (-1.0, C.ROAD), (cs["road"] + 1.0, C.SIDEWALK),
                       (-(cs["road"] + 1.0), C.SIDEWALK), (cs["sidewalk"] + 5, C.TERRAIN)):
            hit = (g[:, 0] <= sc.ego_x) & (sc.ego_x < g[:, 1]) & (g[:, 2] <= y) & (y < g[:, 3])
            assert hit.sum() == 1 and p.ground_class[hit][0] == cls
        area = ((g[:, 1] - g[:, 0]) * (g[:, 3] - g[:, 2]))
        total = (sc.length + 2 * sc.config.ground_margin) * 2 * sc.config.terrain_extent
        assert area.sum() == pytest.approx(total)
        # lane paint is brighter than asphalt
        road = p.ground_class == C.ROAD
        assert p.ground_reflectivity[road].max() > 0.5 > 0.25 > p.ground_reflectivity[road].min()


def test_sizes_within_class_ranges(scenes):
    seen = set()
    for sc in scenes:
        th = sc.things
        assert set(np.unique(th.cls)) <= set(C.THING_CLASS_IDS.tolist())
        for cls, rng in SIZE_RANGES.items():
            b = th.boxes[th.cls == cls]
            seen |= {cls} if len(b) else set()
            for k, (lo, hi) in enumerate(rng):
                assert np.all((b[:, 3 + k] >= lo) & (b[:, 3 + k] <= hi)), (cls, k)
        for cls, kt in zip(th.cls, th.kitti_type):
            assert kt == C.kitti_type(cls) or (cls == C.TRUCK and kt == "Van")
    assert seen == set(C.THING_CLASS_IDS.tolist())


def test_parts_inside_gt_box(scenes):
    for sc in scenes:
        st = sc.thing_state(0.0)
        pb, pc, pi, _ = sc.part_boxes(st)
        owner = {int(i): k for k, i in enumerate(st.instance)}
        rows = np.array([owner[int(i)] for i in pi])
        gt = st.boxes[rows]
        corners = corners_3d(pb)                                  # (P, 8, 3) world
        c, s = np.cos(gt[:, 6]), np.sin(gt[:, 6])
        dx, dy = corners[..., 0] - gt[:, None, 0], corners[..., 1] - gt[:, None, 1]
        lx, ly = c[:, None] * dx + s[:, None] * dy, -s[:, None] * dx + c[:, None] * dy
        lz = corners[..., 2] - gt[:, None, 2]
        tol = 1e-6
        assert np.all(np.abs(lx) <= gt[:, None, 3] / 2 + tol)
        assert np.all(np.abs(ly) <= gt[:, None, 4] / 2 + tol)
        assert np.all(np.abs(lz) <= gt[:, None, 5] / 2 + tol)
        assert np.array_equal(pc, st.cls[rows])
        # several parts per thing, and the parts span the box (tight-ish GT)
        counts = np.bincount(rows, minlength=len(st.boxes))
        assert counts.min() >= 4
        for k in range(len(st.boxes)):
            m = rows == k
            size = st.boxes[k, 3:6]
            assert lz[m].min() == pytest.approx(-size[2] / 2, abs=1e-6)  # touches ground
            assert lz[m].max() == pytest.approx(size[2] / 2, abs=1e-6)
            assert np.ptp(ly[m]) >= 0.95 * size[1] and np.ptp(lx[m]) >= 0.7 * size[0]


def test_no_bev_overlap_between_things_and_ego(scenes):
    for sc in scenes:
        for t in (0.0, 3.3, 10.0):
            st = sc.thing_state(t)
            b = np.vstack([st.boxes, sc.ego_box(t)])
            area = bev_intersection_area(b, b)
            np.fill_diagonal(area, 0.0)
            assert area.max() == 0.0


def test_things_on_ground_and_in_street(scenes):
    for sc in scenes:
        st = sc.thing_state(0.0)
        b = st.boxes
        assert np.all(np.abs(b[:, 2] - b[:, 5] / 2) < 0.02)
        assert np.all((b[:, 0] >= 0) & (b[:, 0] < sc.length))
        cs = street_cross_section(sc.config)
        assert np.all(np.abs(b[:, 1]) < cs["sidewalk"])
        assert len(np.unique(st.instance)) == len(st.instance) and st.instance.min() >= 1


def test_objects_stay_in_their_lane(scenes):
    for sc in scenes:
        th = sc.things
        in_lane = th.lane >= 0
        b = th.boxes[in_lane]
        ey = 0.5 * (b[:, 3] * np.abs(np.sin(b[:, 6])) + b[:, 4] * np.abs(np.cos(b[:, 6])))
        lanes = [sc.lanes[i] for i in th.lane[in_lane]]
        y_min = np.array([ln.y_min for ln in lanes])
        y_max = np.array([ln.y_max for ln in lanes])
        assert np.all(b[:, 1] - ey >= y_min - 1e-9) and np.all(b[:, 1] + ey <= y_max + 1e-9)
        kinds = {ln.kind: set() for ln in sc.lanes}
        for ln, cls in zip(lanes, th.cls[in_lane]):
            kinds[ln.kind].add(int(cls))
        assert kinds["drive"] <= {C.CAR, C.TRUCK} and kinds["parking"] <= {C.CAR, C.TRUCK}
        assert kinds["bike"] == {C.CYCLIST}
        assert kinds["walk"] | kinds["stand"] == {C.PEDESTRIAN}
        # velocity follows the lane
        v = th.velocity[in_lane]
        assert np.allclose(v[:, 0], [ln.velocity for ln in lanes]) and np.all(v[:, 1] == 0)


def test_yaw_follows_road(scenes):
    for sc in scenes:
        th = sc.things
        veh = np.isin(th.cls, [C.CAR, C.TRUCK, C.CYCLIST]) & (th.lane >= 0)
        yaw = th.boxes[veh, 6]
        dev = np.minimum(np.abs(yaw), np.pi - np.abs(yaw))
        assert np.all(dev <= np.deg2rad(5.0))
        for k in np.flatnonzero(veh):  # moving vehicles face their direction of travel
            vx = th.velocity[k, 0]
            if vx:
                assert np.cos(th.boxes[k, 6]) * vx > 0
        assert np.all(np.abs(th.boxes[:, 6]) <= np.pi)


def test_about_40_things_within_60m(street):
    counts, by_class = [], np.zeros(C.NUM_CLASSES)
    for sc in street:
        st = sc.thing_state(0.0)
        d = np.hypot(st.boxes[:, 0] - sc.ego_x, st.boxes[:, 1] - sc.ego_y)
        counts.append(int((d <= 60).sum()))
        by_class += np.bincount(st.cls[d <= 60], minlength=C.NUM_CLASSES)
    assert all(25 <= c <= 60 for c in counts), counts
    assert 32 <= np.mean(counts) <= 50, counts
    assert np.all(by_class[C.THING_CLASS_IDS] > 0)


def test_moving_traffic_and_crossing_pedestrians(scenes):
    n_cross = 0
    for sc in scenes:
        th = sc.things
        ego_lane = [ln for ln in sc.lanes if ln.kind == "drive" and ln.direction == 1]
        assert any(ln.speed == sc.ego_speed for ln in ego_lane)
        assert np.any(th.velocity[:, 0] > 0) and np.any(th.velocity[:, 0] < 0)
        cross = th.lane < 0
        n_cross += int(cross.sum())
        assert np.all(th.cls[cross] == C.PEDESTRIAN)
        assert np.all(th.velocity[cross, 0] == 0) and np.all(th.velocity[cross, 1] != 0)
        assert np.all(np.isfinite(th.t_birth[cross]) & (th.t_death[cross] > th.t_birth[cross]))
        assert not th.wraps[cross].any()
        for k in np.flatnonzero(cross):  # alive exactly during the crossing window
            assert k in sc.thing_state(th.t_birth[k]).index
            assert k in sc.thing_state(th.t_death[k]).index
            assert k not in sc.thing_state(th.t_birth[k] - 0.1).index
            assert k not in sc.thing_state(th.t_death[k] + 0.1).index
    assert n_cross >= len(SEEDS)  # usually all 3 attempted per scene are placed


def test_wrap_around_gives_new_instance_id():
    sc = generate_scene(2)
    th = sc.things
    k = int(np.flatnonzero(th.velocity[:, 0] > 0)[0])
    t_wrap = (sc.length - th.boxes[k, 0]) / th.velocity[k, 0]
    before, after = sc.thing_state(t_wrap - 0.05), sc.thing_state(t_wrap + 0.05)
    ib, ia = (int(s.instance[s.index == k][0]) for s in (before, after))
    assert ib == k + 1 and ia == k + 1 + len(th)
    xa = after.boxes[after.index == k][0, 0]
    assert xa < 1.0
    for s in (before, after):
        assert len(np.unique(s.instance)) == len(s.instance)


def test_config_variants_and_validation():
    cfg = SceneConfig(length=150.0, lanes_per_direction=2, ego_lane=1, bike_lane_width=0.0,
                      parking_width=0.0, crossing_pedestrians=0)
    sc = generate_scene(1, cfg)
    th = sc.things
    assert not np.isin(th.cls, [C.CYCLIST]).any()
    assert np.all(th.velocity[np.isin(th.cls, [C.CAR, C.TRUCK]), 0] != 0)  # nothing parked
    assert sc.ego_y == pytest.approx(-cfg.lane_width / 2)   # inner +x lane
    st = sc.thing_state(0.0)
    b = np.vstack([st.boxes, sc.ego_box()])
    area = bev_intersection_area(b, b)
    np.fill_diagonal(area, 0.0)
    assert area.max() == 0.0
    sc0 = generate_scene(1, SceneConfig(moving_per_100m=0, parked_per_100m=0,
                                        cyclists_per_100m=0, pedestrians_per_100m=0,
                                        crossing_pedestrians=0))
    assert len(sc0.things) == 0 and len(sc0.thing_state(0.0).boxes) == 0
    for bad in (dict(lane_width=2.0), dict(ego_lane=1), dict(parking_width=1.0),
                dict(sidewalk_width=1.5), dict(length=-1.0), dict(setback_min=7.0),
                dict(hedge_prob=1.5), dict(flush_building_prob=-0.1),
                dict(building_gap_range=(5.0, 2.0)), dict(building_width_range=(0.0, 3.0))):
        with pytest.raises(ValueError):
            generate_scene(0, SceneConfig(**bad))


def test_ego_box():
    sc = generate_scene(0)
    b = sc.ego_box(2.0)
    assert b[0] == pytest.approx(sc.ego_x + 2.0 * sc.ego_speed)
    assert tuple(b[3:6]) == EGO_SIZE and b[6] == 0.0


# ------------------------------------------------------------------------- scene types

def test_scene_types_and_lookup():
    assert list(SCENE_TYPES) == ["street", "suburban"]
    assert SCENE_TYPES["street"] == SceneConfig()   # the default: what the splits use
    for cfg in SCENE_TYPES.values():
        cfg.validate()
    assert scene_config() == SceneConfig() and scene_config(None) == SceneConfig()
    assert scene_config("suburban") is SCENE_TYPES["suburban"]
    cfg = SceneConfig(length=120.0)
    assert scene_config(cfg) is cfg
    with pytest.raises(KeyError, match="street, suburban"):
        scene_config("rural")
    with pytest.raises(TypeError):
        SCENE_TYPES["mine"] = cfg   # read-only


def _main_buildings(sc: Scene) -> np.ndarray:
    """Building boxes standing on the ground (not the roof structures on top)."""
    p = sc.static
    b = p.boxes[p.box_class == C.BUILDING]
    return b[np.abs(b[:, 2] - b[:, 5] / 2) < 1e-9]


def test_suburban_is_open_and_green(street, suburban):
    cfg = SCENE_TYPES["suburban"]
    for a, b in zip(street, suburban):
        assert a.length == b.length
        ba, bb = _main_buildings(a), _main_buildings(b)
        cs = street_cross_section(b.config)
        # houses far back behind front yards; the street has buildings at the sidewalk
        front_a = np.abs(ba[:, 1]) - ba[:, 4] / 2 - street_cross_section(a.config)["sidewalk"]
        front_b = np.abs(bb[:, 1]) - bb[:, 4] / 2 - cs["sidewalk"]
        assert front_a.min() < 0.5 and np.all(front_b >= cfg.setback_min - 1e-9)
        # street frontage built up: under half the street's, and low houses
        assert bb[:, 3].sum() < 0.5 * ba[:, 3].sum()
        assert bb[:, 5].max() <= cfg.building_height_range[1]
        # vegetation: several times the street's ellipsoids (hedges, bushes, trees)
        assert len(b.static.ellipsoids) > 3 * len(a.static.ellipsoids)
        # parked cars along both curbs, fewer pedestrians
        for sc in (a, b):
            parking = [i for i, ln in enumerate(sc.lanes) if ln.kind == "parking"]
            assert {sc.lanes[i].side for i in parking} == {-1, 1}
            for i in parking:
                assert np.isin(sc.things.cls[sc.things.lane == i], [C.CAR, C.TRUCK]).sum() >= 10
    n_ped = [sum(int((sc.things.cls == C.PEDESTRIAN).sum()) for sc in scs)
             for scs in (street, suburban)]
    assert n_ped[1] < 0.5 * n_ped[0]   # measured 64 vs 171


def test_vegetation_clear_of_buildings(scenes):
    for sc in scenes:
        p = sc.static
        b, e = p.boxes[p.box_class == C.BUILDING], p.ellipsoids   # all axis-aligned
        assert np.all(b[:, 6] == 0)
        ox = (np.minimum(b[:, None, 0] + b[:, None, 3] / 2, e[None, :, 0] + e[None, :, 3])
              - np.maximum(b[:, None, 0] - b[:, None, 3] / 2, e[None, :, 0] - e[None, :, 3]))
        oy = (np.minimum(b[:, None, 1] + b[:, None, 4] / 2, e[None, :, 1] + e[None, :, 4])
              - np.maximum(b[:, None, 1] - b[:, None, 4] / 2, e[None, :, 1] - e[None, :, 4]))
        assert np.minimum(ox, oy).max() < 0


def _hedge_pieces(sc: Scene) -> np.ndarray:
    """Vegetation ellipsoids whose near side is 0.3 m behind the sidewalk (hedges)."""
    e = sc.static.ellipsoids
    sw = street_cross_section(sc.config)["sidewalk"]
    return e[np.abs(np.abs(e[:, 1]) - e[:, 4] - (sw + 0.3)) < 1e-9]


def test_hedges_line_the_yards(street):
    assert all(len(_hedge_pieces(sc)) == 0 for sc in street)   # hedge_prob 0
    cfg = dataclasses.replace(SCENE_TYPES["suburban"], hedge_prob=1.0)
    for seed in range(3):
        sc = generate_scene(seed, cfg)
        h = _hedge_pieces(sc)
        # every gap and front yard (all set back >= 12 m) is hedged instead of fenced
        assert not np.any(sc.static.box_class == C.FENCE)
        for side in (-1, 1):
            hs = h[np.sign(h[:, 1]) == side]
            # consecutive pieces overlap: the hedges run along nearly the whole street
            x = np.arange(0.0, sc.length, 0.05)
            covered = (np.abs(x[:, None] - hs[None, :, 0]) <= hs[None, :, 3]).any(axis=1)
            assert covered.mean() > 0.9
        top = h[:, 2] + h[:, 5]
        assert np.all(h[:, 2] - h[:, 5] <= 0) and np.all((top > 1.0) & (top <= 2.2 + 1e-9))
    # the suburban type hedges some of them
    n = [len(_hedge_pieces(generate_scene(s, SCENE_TYPES["suburban"]))) for s in range(3)]
    assert min(n) > 50
