"""Tests for lidar_sim.sequence (ego drive, moving objects, sensor-frame primitives)."""
import dataclasses

import numpy as np
import pytest

from lidar_quality_core.iou import bev_intersection_area
from lidar_sim import classes as C
from lidar_sim.primitives import Primitives
from lidar_sim.scene import SCENE_TYPES, SceneConfig
from lidar_sim.sequence import (DEFAULT_START_NS, FramePrimitives, Sequence,
                                generate_sequence)

N_FRAMES = 60
FAR = 1e5  # a max_range that culls nothing


@pytest.fixture(scope="module", params=list(SCENE_TYPES))
def seq(request) -> Sequence:
    """A drive through each scene type: every check below holds for all of them."""
    return generate_sequence(3, N_FRAMES, SCENE_TYPES[request.param])


def _world(f: FramePrimitives, xyz: np.ndarray) -> np.ndarray:
    return xyz + f.ego_pose[:3, 3]


def _by_instance(f: FramePrimitives):
    return {int(i): k for k, i in enumerate(f.gt_instance)}


def test_stamps_and_ego_motion(seq):
    assert len(seq) == N_FRAMES
    for i in (0, 1, 17):
        assert seq.stamp_ns(i) == DEFAULT_START_NS + i * 100_000_000
    p0, p1 = seq.ego_pose(0), seq.ego_pose(1)
    assert np.array_equal(p0[:3, :3], np.eye(3))           # yaw exactly 0
    step = p1[:3, 3] - p0[:3, 3]
    assert step == pytest.approx([seq.scene.ego_speed * 0.1, 0.0, 0.0])
    assert p0[2, 3] == pytest.approx(1.73)
    f = seq.frame(5)
    assert f.stamp_ns == seq.stamp_ns(5) and f.index == 5
    assert np.array_equal(f.ego_pose, seq.ego_pose(5))
    with pytest.raises(IndexError):
        seq.frame(N_FRAMES)
    g = generate_sequence(3, 3, start_ns=5, dt=0.05)
    assert [g.stamp_ns(i) for i in range(3)] == [5, 50_000_005, 100_000_005]


def test_ego_stays_away_from_street_ends(seq):
    sc = seq.scene
    xs = [seq.ego_position(i)[0] for i in (0, N_FRAMES - 1)]
    assert xs[0] >= 130.0 - 1e-9 and sc.length - xs[1] >= 130.0 - 1e-9
    long = generate_sequence(0, 400, SceneConfig(length=100.0, crossing_pedestrians=0))
    assert long.scene.length >= 2 * 130 + 39.9 * long.scene.ego_speed


def test_ground_and_sensor_height(seq):
    for h in (1.73, 2.0):
        f = seq.frame(3, sensor_height=h)
        p = f.primitives
        assert p.ground_z == pytest.approx(-h) and f.sensor_height == h
        assert f.ego_pose[2, 3] == pytest.approx(h)
        gt = f.gt_boxes
        assert np.allclose(gt[:, 2] - gt[:, 5] / 2, -h, atol=0.02)   # things on the ground
        assert np.allclose(p.cylinders[:, 2], -h)                     # poles / trunks too
        thing = np.isin(p.box_class, C.THING_CLASS_IDS)
        assert np.all(p.boxes[thing, 2] - p.boxes[thing, 5] / 2 >= -h - 1e-6)


def test_static_world_points_transform_between_frames(seq):
    sc = seq.scene
    fa, fb = seq.frame(0, max_range=FAR), seq.frame(25, max_range=FAR)
    n = len(sc.static.boxes)
    for f in (fa, fb):
        p = f.primitives
        assert np.allclose(_world(f, p.boxes[:n, :3]), sc.static.boxes[:, :3])
        assert np.array_equal(p.boxes[:n, 3:], sc.static.boxes[:, 3:])
        assert np.allclose(_world(f, p.ellipsoids[:, :3]), sc.static.ellipsoids[:, :3])
        assert np.allclose(p.cylinders[:, :2] + f.ego_pose[:2, 3], sc.static.cylinders[:, :2])
    # the same static point seen from two frames differs by the ego displacement
    d = fb.ego_pose[:3, 3] - fa.ego_pose[:3, 3]
    assert np.allclose(fa.primitives.boxes[:n, :3] - fb.primitives.boxes[:n, :3], d)
    assert d[0] == pytest.approx(25 * 0.1 * sc.ego_speed)


def test_moving_objects_advance_by_velocity(seq):
    moved = 0
    for i in (0, 20, 41):
        fa, fb = seq.frame(i), seq.frame(i + 1)
        ib = _by_instance(fb)
        for ka, inst in enumerate(fa.gt_instance):
            kb = ib.get(int(inst))
            if kb is None:
                continue
            wa = _world(fa, fa.gt_boxes[ka, :3])
            wb = _world(fb, fb.gt_boxes[kb, :3])
            v = fa.gt_velocity[ka]
            assert wb[:2] - wa[:2] == pytest.approx(v * 0.1, abs=1e-6)
            assert wb[2] == pytest.approx(wa[2])
            assert np.array_equal(fa.gt_boxes[ka, 3:], fb.gt_boxes[kb, 3:])  # size, yaw
            assert fa.gt_class[ka] == fb.gt_class[kb]
            assert fa.gt_kitti_type[ka] == fb.gt_kitti_type[kb]
            moved += bool(np.any(v != 0))
    assert moved > 20


def test_parked_objects_fixed_in_world(seq):
    fa, fb = seq.frame(0), seq.frame(N_FRAMES - 1)
    ib = _by_instance(fb)
    static = np.flatnonzero(np.all(fa.gt_velocity == 0, axis=1))
    common = [k for k in static if int(fa.gt_instance[k]) in ib]
    assert len(common) > 10
    for ka in common:
        kb = ib[int(fa.gt_instance[ka])]
        assert np.allclose(_world(fa, fa.gt_boxes[ka, :3]), _world(fb, fb.gt_boxes[kb, :3]))
    # relative to the moving sensor they shift by the ego displacement
    assert np.any(np.abs(fa.gt_boxes[common, 0] - fb.gt_boxes[[ib[int(fa.gt_instance[k])]
                                                                for k in common], 0]) > 1)


def test_instance_ids_stable_and_unique(seq):
    frames = [seq.frame(i, max_range=FAR) for i in range(0, N_FRAMES, 3)]
    ref = {}
    for f in frames:
        assert len(np.unique(f.gt_instance)) == len(f.gt_instance)
        assert f.gt_instance.min() >= 1
        for k, inst in enumerate(f.gt_instance):
            key = (int(f.gt_class[k]), *np.round(f.gt_boxes[k, 3:6], 9))
            assert ref.setdefault(int(inst), key) == key
    # thing parts carry the instance and class of their GT box
    f = frames[0]
    p = f.primitives
    thing = p.box_instance > 0
    assert set(np.unique(p.box_instance[thing])) == set(f.gt_instance.tolist())
    cls_of = dict(zip(f.gt_instance.tolist(), f.gt_class.tolist()))
    assert all(cls_of[i] == c for i, c in zip(p.box_instance[thing], p.box_class[thing]))
    assert np.all(np.isin(p.box_class[~thing], C.STUFF_CLASS_IDS))


def test_no_overlap_over_time(seq):
    for i in range(0, N_FRAMES, 4):
        st = seq.scene.thing_state(seq.time(i))
        b = np.vstack([st.boxes, seq.ego_box(i)])
        area = bev_intersection_area(b, b)
        np.fill_diagonal(area, 0.0)
        assert area.max() == 0.0


def test_range_culling(seq):
    f_all, f = seq.frame(10, max_range=FAR), seq.frame(10, max_range=40.0)
    p = f.primitives
    assert len(p.boxes) < len(f_all.primitives.boxes)
    assert len(f.gt_boxes) < len(f_all.gt_boxes)
    r = 0.5 * np.hypot(p.boxes[:, 3], p.boxes[:, 4])
    assert np.all(np.hypot(p.boxes[:, 0], p.boxes[:, 1]) - r <= 40.0 + 1e-9)
    assert np.all(np.hypot(p.cylinders[:, 0], p.cylinders[:, 1]) - p.cylinders[:, 4] <= 40.0)
    re = np.maximum(p.ellipsoids[:, 3], p.ellipsoids[:, 4])
    assert np.all(np.hypot(p.ellipsoids[:, 0], p.ellipsoids[:, 1]) - re <= 40.0 + 1e-9)
    gt = f.gt_boxes
    assert np.all(np.hypot(gt[:, 0], gt[:, 1]) - 0.5 * np.hypot(gt[:, 3], gt[:, 4]) <= 40.0)
    # every GT box kept at 40 m is also in the unculled frame, identically
    ia = _by_instance(f_all)
    for k, inst in enumerate(f.gt_instance):
        assert np.array_equal(f.gt_boxes[k], f_all.gt_boxes[ia[int(inst)]])
    g = p.ground_regions
    assert np.all(np.abs(g) <= 41.0 + 1e-9)
    assert np.all(g[:, 1] > g[:, 0]) and np.all(g[:, 3] > g[:, 2])
    # the sensor stands on the ego lane's asphalt
    under = (g[:, 0] <= 0) & (0 < g[:, 1]) & (g[:, 2] <= 0) & (0 < g[:, 3])
    assert under.sum() == 1 and p.ground_class[under][0] == C.ROAD


def test_frame_primitives_dtypes(seq):
    f = seq.frame(7)
    p = f.primitives
    assert isinstance(p, Primitives)
    for name in ("box_class", "box_instance", "cylinder_class", "cylinder_instance",
                 "ellipsoid_class", "ellipsoid_instance", "ground_class"):
        assert getattr(p, name).dtype == np.int32
    for name in ("boxes", "cylinders", "ellipsoids", "ground_regions", "box_reflectivity"):
        assert getattr(p, name).dtype == np.float64
    assert len(p.box_class) == len(p.boxes) == len(p.box_reflectivity)
    assert len(p.ellipsoid_porosity) == len(p.ellipsoids)
    assert f.gt_boxes.shape == (len(f.gt_class), 7) and f.gt_velocity.shape == (len(f.gt_class), 2)
    assert f.gt_class.dtype == np.int32 and f.gt_instance.dtype == np.int32
    assert len(f.gt_kitti_type) == len(f.gt_class)


def test_determinism():
    a, b, c = (generate_sequence(s, 5) for s in (11, 11, 12))
    fa, fb, fc = a.frame(4), b.frame(4), c.frame(4)
    for fld in dataclasses.fields(Primitives):
        x, y = getattr(fa.primitives, fld.name), getattr(fb.primitives, fld.name)
        assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
    assert np.array_equal(fa.gt_boxes, fb.gt_boxes)
    assert np.array_equal(fa.gt_instance, fb.gt_instance)
    assert not np.array_equal(fa.gt_boxes.shape, fc.gt_boxes.shape) or not np.array_equal(
        fa.gt_boxes, fc.gt_boxes)


def test_crossing_pedestrian_motion():
    seq = generate_sequence(4, 150)
    th = seq.scene.things
    cross = np.flatnonzero(th.lane < 0)
    assert len(cross) >= 1
    k = int(cross[0])
    i0 = int(round(th.t_birth[k] / seq.dt))
    frames = [i for i in range(max(i0, 0), min(i0 + 5, len(seq)))]
    inst = k + 1
    ys = []
    for i in frames:
        f = seq.frame(i, max_range=FAR)
        m = f.gt_instance == inst
        assert m.sum() == 1
        ys.append(_world(f, f.gt_boxes[m][0, :3])[1])
        assert abs(abs(f.gt_boxes[m][0, 6]) - np.pi / 2) < 0.1   # walking across
    assert np.allclose(np.diff(ys), th.velocity[k, 1] * seq.dt)
