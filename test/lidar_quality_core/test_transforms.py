"""Rigid transforms and the transform buffer: hand-computed cases, scipy's Rotation as an
independent check of the quaternion algebra, tree chaining, interpolation, refusals."""
import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from lidar_quality_core.transforms import (ConnectivityError, ExtrapolationError, Transform,
                                           TransformBuffer, TransformError, add_tf_message,
                                           interpolate)

RNG = np.random.default_rng(16)


def random_transform(tilt=True):
    q = Rotation.random(random_state=RNG).as_quat() if tilt else Rotation.from_euler(
        "z", RNG.uniform(-np.pi, np.pi)).as_quat()
    return Transform(RNG.normal(size=3) * 5, q)


def scipy_apply(t: Transform, p):
    return Rotation.from_quat(t.rotation).apply(p) + t.translation


def test_hand_computed_yaw_and_translation():
    t = Transform.from_yaw(math.pi / 2, (1.0, 2.0, 3.0))  # x -> y, then shift
    np.testing.assert_allclose(t.apply_points([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
                               [[1.0, 3.0, 3.0], [0.0, 2.0, 3.0]], atol=1e-12)
    np.testing.assert_allclose(t.inverse().apply_points([[1.0, 3.0, 3.0]]), [[1.0, 0.0, 0.0]],
                               atol=1e-12)
    assert t.rpy() == pytest.approx((0.0, 0.0, math.pi / 2))
    # a mount 1.2 m forward, 1.8 m up, 90 deg pitch-free: the matrix by hand
    np.testing.assert_allclose(t.matrix(), [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3],
                                            [0, 0, 0, 1]], atol=1e-12)


def test_quaternion_normalised_and_refused():
    t = Transform([0, 0, 0], [0, 0, 2, 0])  # 180 deg about z, not unit
    np.testing.assert_allclose(t.rotation, [0, 0, 1, 0])
    with pytest.raises(ValueError, match="not a rigid transform"):
        Transform([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="not a rigid transform"):
        Transform([np.nan, 0, 0], [0, 0, 0, 1])


@pytest.mark.parametrize("seed", range(5))
def test_compose_invert_apply_match_scipy(seed):
    a, b = random_transform(), random_transform()
    p = RNG.normal(size=(50, 3)) * 20
    np.testing.assert_allclose(a.apply_points(p), scipy_apply(a, p), atol=1e-9)
    ab = a * b
    np.testing.assert_allclose(ab.apply_points(p), scipy_apply(a, scipy_apply(b, p)), atol=1e-9)
    r = Rotation.from_quat(a.rotation) * Rotation.from_quat(b.rotation)
    np.testing.assert_allclose(ab.rotation_matrix(), r.as_matrix(), atol=1e-12)
    np.testing.assert_allclose((a * a.inverse()).matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(a.inverse().matrix(), np.linalg.inv(a.matrix()), atol=1e-9)
    assert Transform.from_matrix(a.matrix()).close_to(a)
    # ZYX angles as scipy's intrinsic "ZYX" (yaw, pitch, roll)
    yaw, pitch, roll = Rotation.from_quat(a.rotation).as_euler("ZYX")
    assert a.rpy() == pytest.approx((roll, pitch, yaw), abs=1e-9)


def test_apply_boxes_yaw_transform_keeps_boxes_exact():
    t = Transform.from_yaw(0.3, (1.5, -0.2, 1.8))
    boxes = np.array([[10.0, 2.0, -1.0, 4.2, 1.8, 1.5, 3.0],
                      [-5.0, 7.0, -0.5, 0.8, 0.6, 1.7, -0.1]])
    out, issue = t.apply_boxes(boxes)
    assert issue is None
    np.testing.assert_allclose(out[:, :3], scipy_apply(t, boxes[:, :3]), atol=1e-12)
    np.testing.assert_allclose(out[:, 3:6], boxes[:, 3:6])
    # 3.0 + 0.3 wraps to 3.3 - 2 pi
    np.testing.assert_allclose(out[:, 6], [3.3 - 2 * np.pi, 0.2], atol=1e-12)
    # the box corners move as rigid points: compare against the transformed corners
    c, s = np.cos(boxes[0, 6]), np.sin(boxes[0, 6])
    corner = boxes[0, :3] + np.array([c * 2.1 - s * 0.9, s * 2.1 + c * 0.9, 0.75])
    c2, s2 = np.cos(out[0, 6]), np.sin(out[0, 6])
    corner2 = out[0, :3] + np.array([c2 * 2.1 - s2 * 0.9, s2 * 2.1 + c2 * 0.9, 0.75])
    np.testing.assert_allclose(corner2, t.apply_points(corner[None])[0], atol=1e-12)


def test_apply_boxes_tilted_transform_is_reported_yaw_only():
    t = Transform([0, 0, 0], Rotation.from_euler("ZYX", [0.5, 0.1, 0.0]).as_quat())
    out, issue = t.apply_boxes(np.array([[10.0, 0, 0, 4, 2, 1.5, 0.0]]))
    assert issue is not None and "5.7 deg" in issue and "yaw only" in issue
    np.testing.assert_allclose(out[0, :3], scipy_apply(t, [[10.0, 0, 0]])[0], atol=1e-12)
    assert out[0, 6] == pytest.approx(0.5)
    small = Transform([0, 0, 0], Rotation.from_euler("ZYX", [0.5, 0.01, 0.0]).as_quat())
    assert small.apply_boxes(np.zeros((1, 7)))[1] is None  # 0.57 deg: within tolerance


def test_interpolation_matches_scipy_slerp():
    a, b = random_transform(), random_transform()
    for f in (0.0, 0.25, 0.5, 0.9, 1.0):
        m = interpolate(a, b, f)
        ref = Slerp([0, 1], Rotation.from_quat([a.rotation, b.rotation]))([f])
        np.testing.assert_allclose(m.rotation_matrix(), ref.as_matrix()[0], atol=1e-9)
        np.testing.assert_allclose(m.translation, (1 - f) * a.translation + f * b.translation)


def tree():
    """map -> odom -> base_link -> lidar (static), base_link -> camera (static)."""
    buf = TransformBuffer(history_s=2.0, max_samples=50, extrapolation_tolerance_s=0.01)
    lidar = Transform([1.2, 0.0, 1.8], Rotation.from_euler("z", 0.02).as_quat())
    camera = Transform([1.5, 0.1, 1.3], Rotation.from_euler("ZYX", [0, 0, -1.57]).as_quat())
    buf.set_transform("base_link", "lidar", lidar, static=True)
    buf.set_transform("/base_link", "camera", camera, static=True)  # leading '/' ignored
    for k in range(11):  # odom -> base_link: driving along x at 10 m/s, turning 0.1 rad/s
        t_ns = 1_000_000_000 + k * 100_000_000
        buf.set_transform("odom", "base_link", Transform.from_yaw(0.01 * k, (1.0 * k, 0, 0)),
                          t_ns)
    buf.set_transform("map", "odom", Transform([100.0, 50.0, 0.0], [0, 0, 0, 1]), static=True)
    return buf, lidar, camera


def test_lookup_chains_through_the_tree():
    buf, lidar, camera = tree()
    assert buf.lookup("lidar", "lidar").is_identity()
    assert buf.lookup("base_link", "lidar").close_to(lidar)
    assert buf.lookup("lidar", "base_link").close_to(lidar.inverse())
    # siblings: camera -> lidar goes through base_link
    assert buf.lookup("lidar", "camera", 5).close_to(lidar.inverse() * camera)
    # up through a timestamped edge at one of its samples
    t = buf.lookup("map", "lidar", 1_300_000_000)
    ref = (Transform([100.0, 50, 0], [0, 0, 0, 1]) * Transform.from_yaw(0.03, (3.0, 0, 0))
           * lidar)
    assert t.close_to(ref)
    p = RNG.normal(size=(5, 3))
    np.testing.assert_allclose(buf.lookup("lidar", "map", 1_300_000_000).apply_points(
        t.apply_points(p)), p, atol=1e-9)
    assert set(buf.frames()) == {"map", "odom", "base_link", "lidar", "camera"}
    assert buf.parent("lidar") == "base_link"


def test_lookup_interpolates_between_samples():
    buf, lidar, _ = tree()
    t = buf.lookup("odom", "base_link", 1_250_000_000)  # halfway between k=2 and k=3
    assert t.close_to(Transform.from_yaw(0.025, (2.5, 0, 0)))


def test_latest_and_extrapolation():
    buf, _, _ = tree()
    assert buf.lookup("odom", "base_link").close_to(Transform.from_yaw(0.1, (10.0, 0, 0)))
    assert buf.lookup("odom", "base_link", 0).close_to(Transform.from_yaw(0.1, (10.0, 0, 0)))
    # within the 10 ms tolerance: the nearest sample
    assert buf.lookup("odom", "base_link", 2_005_000_000).close_to(
        Transform.from_yaw(0.1, (10.0, 0, 0)))
    with pytest.raises(ExtrapolationError) as e:
        buf.lookup("lidar", "odom", 2_500_000_000)
    msg = str(e.value)
    assert "'odom'" in msg and "'lidar'" in msg and "2.500000000 s" in msg
    assert "'odom' -> 'base_link'" in msg and e.value.stamp_ns == 2_500_000_000
    with pytest.raises(ExtrapolationError):
        buf.lookup("odom", "base_link", 900_000_000)


def test_unknown_and_disconnected_frames_name_them():
    buf, _, _ = tree()
    with pytest.raises(ConnectivityError, match="frame 'velodyne' is unknown") as e:
        buf.lookup("velodyne", "base_link", 10)
    assert isinstance(e.value, TransformError) and e.value.target == "velodyne"
    buf.set_transform("world", "radar", Transform.identity(), static=True)
    with pytest.raises(ConnectivityError, match="different trees"):
        buf.lookup("lidar", "radar")
    empty = TransformBuffer()
    with pytest.raises(ConnectivityError, match="no transform received"):
        empty.lookup("a", "b", 1)
    assert not empty.can_transform("a", "b") and buf.can_transform("map", "camera")


def test_history_is_bounded_and_out_of_order_samples_kept_sorted():
    buf = TransformBuffer(history_s=1.0, max_samples=5)
    for k in [0, 2, 1, 4, 3]:  # out of order
        buf.set_transform("odom", "base", Transform.from_yaw(0, (k, 0, 0)), k * 100_000_000)
    assert buf.lookup("odom", "base", 150_000_000).translation[0] == pytest.approx(1.5)
    for k in range(5, 40):
        buf.set_transform("odom", "base", Transform.from_yaw(0, (k, 0, 0)), k * 100_000_000)
    edge = buf._edges["base"]
    assert len(edge.stamps) == 5 and list(edge.stamps) == sorted(edge.stamps)
    with pytest.raises(ExtrapolationError):
        buf.lookup("odom", "base", 100_000_000)
    # time span bound: samples older than history_s before the newest go
    b2 = TransformBuffer(history_s=0.25, max_samples=100)
    for k in range(10):
        b2.set_transform("odom", "base", Transform.identity(), k * 100_000_000)
    assert list(b2._edges["base"].stamps) == [700_000_000, 800_000_000, 900_000_000]


def test_new_parent_replaces_and_cycles_refused():
    buf = TransformBuffer()
    buf.set_transform("a", "b", Transform.identity(), static=True)
    buf.set_transform("b", "c", Transform.identity(), static=True)
    with pytest.raises(ValueError, match="cycle"):
        buf.set_transform("c", "a", Transform.identity(), static=True)
    with pytest.raises(ValueError, match="bad transform frames"):
        buf.set_transform("a", "a", Transform.identity())
    buf.set_transform("x", "c", Transform.from_yaw(0, (1, 0, 0)), static=True)
    assert buf.parent("c") == "x"


def _ts(parent, child, sec, tx, q=(0.0, 0.0, 0.0, 1.0)):
    return NS(header=NS(frame_id=parent, stamp=NS(sec=sec, nanosec=0)), child_frame_id=child,
              transform=NS(translation=NS(x=tx, y=0.0, z=0.0),
                           rotation=NS(x=q[0], y=q[1], z=q[2], w=q[3])))


def test_add_tf_message_reports_bad_entries():
    buf = TransformBuffer()
    bad = add_tf_message(buf, NS(transforms=[_ts("base_link", "lidar", 0, 1.0),
                                             _ts("base_link", "cam", 0, 1.0, (0, 0, 0, 0)),
                                             _ts("base_link", "base_link", 0, 1.0)]),
                         static=True)
    assert len(bad) == 2 and "'cam'" in bad[0] and "bad transform frames" in bad[1]
    assert buf.lookup("base_link", "lidar").translation[0] == 1.0
