"""A driving sequence through a generated street: per-frame primitives in the SENSOR frame.

Frames are ``dt`` apart (10 Hz by default); frame i is at scene time ``t = i * dt`` and
stamped ``start_ns + i * round(dt * 1e9)``. The ego drives along +x in its lane at constant
speed with yaw exactly 0 (the street is straight along x): the sensor frame is the world
frame translated to the sensor (ego position + mount height), so ground regions stay
axis-aligned rectangles and the ground plane is at ``z = -sensor_height``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .primitives import Primitives
from .scene import Scene, SceneConfig, generate_scene

__all__ = ["FramePrimitives", "Sequence", "generate_sequence", "DEFAULT_START_NS",
           "DEFAULT_SENSOR_HEIGHT"]

DEFAULT_START_NS = 1_700_000_000_000_000_000  # an arbitrary fixed epoch (2023-11-14)
DEFAULT_SENSOR_HEIGHT = 1.73                  # KITTI's HDL-64 mount height


@dataclass
class FramePrimitives:
    """One frame: what the ray caster consumes plus ground truth, all in the sensor frame.

    ``gt_*`` rows are the things whose BEV footprint comes within ``max_range`` of the
    sensor (the same things whose parts are in ``primitives``). ``gt_boxes`` (M, 7) x, y, z
    (box centre), l, w, h, yaw; ``gt_velocity`` (M, 2) world velocity (vx, vy), which is
    also its sensor-frame value since the sensor frame is not rotated.
    """

    index: int
    stamp_ns: int
    ego_pose: np.ndarray       # (4, 4) world-from-sensor
    sensor_height: float
    primitives: Primitives
    gt_boxes: np.ndarray
    gt_class: np.ndarray       # (M,) int32, our class ids
    gt_instance: np.ndarray    # (M,) int32, >= 1
    gt_velocity: np.ndarray    # (M, 2)
    gt_kitti_type: tuple[str, ...]


def _cull(centres_xy: np.ndarray, radius: np.ndarray, sensor_xy, max_range: float) -> np.ndarray:
    d = np.hypot(centres_xy[:, 0] - sensor_xy[0], centres_xy[:, 1] - sensor_xy[1])
    return d - radius <= max_range


@dataclass
class Sequence:
    """Ego motion through ``scene``; ``frame(i)`` gives the sensor-frame primitives."""

    scene: Scene
    n_frames: int
    dt: float = 0.1
    start_ns: int = DEFAULT_START_NS

    def __len__(self) -> int:
        return self.n_frames

    def _check(self, i: int) -> int:
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} out of range [0, {self.n_frames})")
        return int(i)

    def time(self, i: int) -> float:
        """Scene time (s) of frame i."""
        return self._check(i) * self.dt

    def stamp_ns(self, i: int) -> int:
        """Timestamp of frame i in nanoseconds."""
        return self.start_ns + self._check(i) * int(round(self.dt * 1e9))

    def ego_position(self, i: int) -> np.ndarray:
        """(3,) world position of the ego at frame i, on the ground (z = 0)."""
        t = self.time(i)
        return np.array([self.scene.ego_x + self.scene.ego_speed * t, self.scene.ego_y, 0.0])

    def ego_pose(self, i: int, sensor_height: float = DEFAULT_SENSOR_HEIGHT) -> np.ndarray:
        """(4, 4) world-from-sensor pose of frame i (yaw 0: a pure translation)."""
        pose = np.eye(4)
        pose[:3, 3] = self.ego_position(i) + (0.0, 0.0, sensor_height)
        return pose

    def ego_box(self, i: int) -> np.ndarray:
        """(7,) ego car box in the world frame at frame i."""
        return self.scene.ego_box(self.time(i))

    def frame(self, i: int, sensor_height: float = DEFAULT_SENSOR_HEIGHT,
              max_range: float = 120.0) -> FramePrimitives:
        """Primitives and GT of frame i in the sensor frame.

        Primitives (and GT things) whose BEV circle (centre distance minus BEV radius) lies
        farther than ``max_range`` from the sensor are dropped, so a thing at the range
        limit may keep only some of its parts; ground regions are clipped to the square of
        half-width ``max_range + 1`` around the sensor.
        """
        sc = self.scene
        t = self.time(i)
        pose = self.ego_pose(i, sensor_height)
        off = pose[:3, 3]
        sxy = off[:2]
        st = sc.static
        rad = sc.static_radius

        kb = _cull(st.boxes[:, :2], rad["boxes"], sxy, max_range)
        kc = _cull(st.cylinders[:, :2], rad["cylinders"], sxy, max_range)
        ke = _cull(st.ellipsoids[:, :2], rad["ellipsoids"], sxy, max_range)

        state = sc.thing_state(t)
        tb = state.boxes
        kt = np.flatnonzero(_cull(tb[:, :2], 0.5 * np.hypot(tb[:, 3], tb[:, 4]), sxy,
                                  max_range))
        pb, pc, pi, pr = sc.part_boxes(state, kt)
        kp = _cull(pb[:, :2], 0.5 * np.hypot(pb[:, 3], pb[:, 4]), sxy, max_range)
        pb, pc, pi, pr = pb[kp], pc[kp], pi[kp], pr[kp]

        boxes = np.concatenate([st.boxes[kb], pb])
        boxes[:, :3] -= off
        cyl = st.cylinders[kc].copy()
        cyl[:, :2] -= sxy
        cyl[:, 2:4] -= off[2]
        ell = st.ellipsoids[ke].copy()
        ell[:, :3] -= off

        # ground regions: clip to the range square, then shift
        g = st.ground_regions
        h = max_range + 1.0
        lo = np.array([sxy[0] - h, sxy[0] - h, sxy[1] - h, sxy[1] - h])
        hi = np.array([sxy[0] + h, sxy[0] + h, sxy[1] + h, sxy[1] + h])
        gc = np.clip(g, lo, hi)
        kg = (gc[:, 1] > gc[:, 0]) & (gc[:, 3] > gc[:, 2])
        gc = gc[kg]
        gc[:, :2] -= sxy[0]
        gc[:, 2:] -= sxy[1]

        prims = Primitives(
            boxes=boxes,
            box_class=np.concatenate([st.box_class[kb], pc]).astype(np.int32),
            box_instance=np.concatenate([st.box_instance[kb], pi]).astype(np.int32),
            box_reflectivity=np.concatenate([st.box_reflectivity[kb], pr]),
            cylinders=cyl, cylinder_class=st.cylinder_class[kc].copy(),
            cylinder_instance=st.cylinder_instance[kc].copy(),
            cylinder_reflectivity=st.cylinder_reflectivity[kc].copy(),
            ellipsoids=ell, ellipsoid_class=st.ellipsoid_class[ke].copy(),
            ellipsoid_instance=st.ellipsoid_instance[ke].copy(),
            ellipsoid_reflectivity=st.ellipsoid_reflectivity[ke].copy(),
            ellipsoid_porosity=st.ellipsoid_porosity[ke].copy(),
            ground_z=st.ground_z - off[2],
            ground_regions=gc, ground_class=st.ground_class[kg].copy(),
            ground_reflectivity=st.ground_reflectivity[kg].copy(),
            default_ground_class=st.default_ground_class,
            default_ground_reflectivity=st.default_ground_reflectivity,
        )
        gt = tb[kt].copy()
        gt[:, :3] -= off
        return FramePrimitives(
            index=int(i), stamp_ns=self.stamp_ns(i), ego_pose=pose,
            sensor_height=float(sensor_height), primitives=prims, gt_boxes=gt,
            gt_class=state.cls[kt].astype(np.int32), gt_instance=state.instance[kt].copy(),
            gt_velocity=state.velocity[kt].copy(),
            gt_kitti_type=tuple(sc.things.kitti_type[j] for j in state.index[kt]))

    def frames(self, sensor_height: float = DEFAULT_SENSOR_HEIGHT, max_range: float = 120.0):
        """Iterate over all frames."""
        for i in range(self.n_frames):
            yield self.frame(i, sensor_height, max_range)


def generate_sequence(seed: int, n_frames: int, config: SceneConfig | None = None, *,
                      dt: float = 0.1, start_ns: int = DEFAULT_START_NS,
                      view_margin: float = 130.0) -> Sequence:
    """Generate a scene and the ego drive through it.

    The street is lengthened if needed so the ego stays ``view_margin`` metres from both
    ends during the whole drive (wrapping objects reappear at the ends, out of sight for
    ``max_range <= view_margin``); unless ``config.ego_x`` is set the drive is centred on
    the street. Crossing pedestrians are planned over the sequence duration.
    """
    if n_frames < 1:
        raise ValueError("n_frames must be >= 1")
    cfg = config or SceneConfig()
    duration = (n_frames - 1) * dt
    travel = cfg.ego_speed * duration
    length = max(cfg.length, travel + 2 * view_margin)
    ego_x = (length - travel) / 2 if cfg.ego_x is None else cfg.ego_x
    cfg = replace(cfg, length=length, ego_x=ego_x, duration=max(duration, dt), dt=dt)
    return Sequence(generate_scene(seed, cfg), n_frames, dt, start_ns)
