"""Procedural straight-street scenes in the WORLD frame (ground plane z = 0).

The street runs along +x from ``x = 0`` to ``x = length``; ``y = 0`` is the road centre
line and +y is left of +x. Traffic is right-handed: lanes at ``y < 0`` drive along +x,
lanes at ``y > 0`` along -x. The cross-section, from the centre outward on each side:
driving lanes, a bike lane, a parking lane (curb), then the sidewalk (curb-side
"furniture" strip with poles, signs and street trees, walking lanes, a strip for standing
pedestrians), then terrain with buildings set back from the sidewalk.

Things (car, truck, pedestrian, cyclist) live in ``Lane``s. Every object of a lane moves
with the lane's velocity (0 for parked cars and standing pedestrians), so gaps along a
lane never change and lanes are laterally disjoint: things cannot collide. Moving lane
objects wrap around the street ends (``x`` modulo ``length``); a wrap counts as a respawn
and gives a new instance id (see ``Scene.thing_state``). Crossing pedestrians walk along
y across the street during a time window, accepted only if they keep clear of every other
thing, the ego and the poles / trunks at every frame time.

Each thing has a ground-truth box ``(x, y, z, l, w, h, yaw)`` (z = box centre, bottom on
the ground) and is made of part boxes (body, cabin, tyres, legs, head, ...) inside it.
Stuff (ground, buildings, fences, vegetation, trunks, poles, signs) has instance 0.

``SCENE_TYPES`` names configurations of this one generator: "street" (the default
``SceneConfig()``, buildings close to the sidewalk) and "suburban" (houses far back behind
hedged front yards, wide gaps of grass, bushes and trees between them).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
from lidar_quality_core.conventions import wrap_angle

from . import classes as C
from .primitives import Primitives

__all__ = ["SceneConfig", "Lane", "Things", "ThingState", "Scene", "generate_scene",
           "SIZE_RANGES", "EGO_SIZE", "street_cross_section", "SCENE_TYPES", "scene_config"]

# Ranges every generated GT box size lies in: class -> ((l), (w), (h)) as (lo, hi).
SIZE_RANGES: dict[int, tuple[tuple[float, float], ...]] = {
    C.CAR: ((3.5, 5.0), (1.6, 2.0), (1.4, 1.7)),
    C.TRUCK: ((5.0, 10.0), (1.9, 2.55), (2.0, 3.5)),     # vans and trucks
    C.PEDESTRIAN: ((0.4, 0.65), (0.5, 0.75), (1.5, 1.95)),
    C.CYCLIST: ((1.6, 1.95), (0.55, 0.7), (1.55, 1.9)),
}
EGO_SIZE = (4.6, 1.9, 1.6)   # l, w, h of the ego car (for clearance only; never rendered)
_LAT_MARGIN = 0.1            # clearance of an object's footprint to its lane's edges
_VAN_MAX_LENGTH = 6.5        # trucks shorter than this are written as KITTI "Van"
_TIME_EPS = 1e-9


@dataclass(frozen=True)
class SceneConfig:
    """Street geometry and object densities. Densities are per 100 m of street."""

    length: float = 300.0
    # cross-section (metres)
    lanes_per_direction: int = 1
    lane_width: float = 3.25
    bike_lane_width: float = 1.5         # 0: no bike lanes, no cyclists
    parking_width: float = 2.3           # 0: no parking lanes, no parked cars
    sidewalk_width: float = 3.5
    furniture_width: float = 0.7         # curb-side sidewalk strip: poles, signs, trees
    standing_width: float = 0.8          # building-side sidewalk strip: standing people
    setback_max: float = 6.0             # building front distance behind the sidewalk
                                         # (see also setback_min, flush_building_prob)
    terrain_extent: float = 150.0        # ground regions reach |y| <= this
    # ego (drives along +x in a +x lane at constant speed; yaw 0)
    ego_speed: float = 10.0
    ego_lane: int = 0                    # index of the +x lane, 0 = next to the bike lane
    ego_x: float | None = None           # ego x at t = 0; None: length / 2
    duration: float = 20.0               # seconds over which crossing people are planned
    dt: float = 0.1                      # frame period: crossings are checked at k * dt
    # traffic
    moving_per_100m: float = 3.0         # per driving lane
    truck_fraction: float = 0.2          # of moving vehicles (half vans, half trucks)
    vehicle_speed_range: tuple[float, float] = (8.0, 14.0)
    parked_per_100m: float = 8.0         # per parking lane
    parked_van_fraction: float = 0.12
    cyclists_per_100m: float = 1.2       # per bike lane
    cyclist_speed_range: tuple[float, float] = (3.5, 6.5)
    pedestrians_per_100m: float = 4.0    # per sidewalk
    standing_fraction: float = 0.25
    walk_speed_range: tuple[float, float] = (0.9, 1.6)
    crossing_pedestrians: int = 3        # attempted; kept only if collision free
    # scenery: buildings alternate with gaps (terrain, maybe fenced) along each side
    building_gap_prob: float = 0.35     # a gap before each building
    building_gap_range: tuple[float, float] = (4.0, 20.0)     # gap length
    building_width_range: tuple[float, float] = (8.0, 35.0)   # frontage along the street
    building_height_range: tuple[float, float] = (5.0, 14.0)
    tall_building_prob: float = 0.3     # of buildings 14-30 m high instead
    flush_building_prob: float = 0.4    # of buildings right at the sidewalk (no setback)
    setback_min: float = 1.0            # others: setback uniform in [setback_min, setback_max]
    fence_prob: float = 0.5             # of gaps fenced along the sidewalk
    hedge_prob: float = 0.0             # of gaps and front yards edged by a hedge instead
    street_trees_per_100m: float = 6.0   # per side
    yard_trees_per_100m: float = 3.0     # per side
    bushes_per_100m: float = 8.0         # per side
    street_light_spacing: float = 30.0
    signs_per_100m: float = 2.5          # per side
    ground_margin: float = 150.0         # ground regions extend this far past the ends
    dash_length: float = 3.0
    dash_gap: float = 6.0

    def validate(self) -> None:
        """Raise ValueError on geometry the generator cannot fill without overlaps."""
        if self.length <= 0 or self.lanes_per_direction < 1:
            raise ValueError("length must be > 0 and lanes_per_direction >= 1")
        if not 0 <= self.ego_lane < self.lanes_per_direction:
            raise ValueError("ego_lane must index a +x driving lane")
        if self.lane_width < SIZE_RANGES[C.TRUCK][1][1] + 0.4:
            raise ValueError("lane_width too small for trucks")
        if 0 < self.parking_width < SIZE_RANGES[C.TRUCK][1][0] + 2 * _LAT_MARGIN + 0.1:
            raise ValueError("parking_width too small for vans")
        if 0 < self.bike_lane_width < SIZE_RANGES[C.CYCLIST][1][1] + 2 * _LAT_MARGIN + 0.1:
            raise ValueError("bike_lane_width too small for cyclists")
        walk = self.sidewalk_width - self.furniture_width - self.standing_width
        if walk < 0.9 or self.standing_width < 0.8 or self.furniture_width < 0.4:
            raise ValueError("sidewalk too narrow for its strips")
        if self.ego_speed < 0:
            raise ValueError("ego_speed must be >= 0")
        for name in ("building_gap_range", "building_width_range", "building_height_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} must be (lo, hi) with 0 < lo <= hi")
        if not 0 <= self.setback_min <= self.setback_max:
            raise ValueError("setback must satisfy 0 <= setback_min <= setback_max")
        for name in ("building_gap_prob", "tall_building_prob", "flush_building_prob",
                     "fence_prob", "hedge_prob"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be a probability")


#: Named scene types. "street": the default, a town street lined with buildings close to
#: the sidewalk. "suburban": an open, KITTI-like residential road: detached houses far back
#: behind front yards with hedges, trees and bushes, wide grass gaps between them, cars
#: parked along both curbs, little traffic and few pedestrians.
SCENE_TYPES: Mapping[str, SceneConfig] = MappingProxyType({
    "street": SceneConfig(),
    "suburban": SceneConfig(
        bike_lane_width=1.2, sidewalk_width=2.5,
        moving_per_100m=1.5, truck_fraction=0.1, parked_per_100m=7.0,
        parked_van_fraction=0.1, cyclists_per_100m=0.6, pedestrians_per_100m=1.0,
        crossing_pedestrians=1,
        building_gap_prob=0.9, building_gap_range=(15.0, 40.0),
        building_width_range=(8.0, 16.0), building_height_range=(4.5, 9.0),
        tall_building_prob=0.0, flush_building_prob=0.0, setback_min=12.0,
        setback_max=30.0, fence_prob=0.3, hedge_prob=0.7,
        street_trees_per_100m=8.0, yard_trees_per_100m=12.0, bushes_per_100m=30.0,
        street_light_spacing=40.0, signs_per_100m=1.0),
})


def scene_config(scene: str | SceneConfig | None = None) -> SceneConfig:
    """The :class:`SceneConfig` of a scene type name (see ``SCENE_TYPES``), a config as
    given, or the default street for None."""
    if scene is None:
        return SceneConfig()
    if isinstance(scene, SceneConfig):
        return scene
    try:
        return SCENE_TYPES[scene]
    except KeyError:
        raise KeyError(f"unknown scene type {scene!r}; known: {', '.join(SCENE_TYPES)}") \
            from None


@dataclass(frozen=True)
class Lane:
    """A longitudinal strip of the street holding one kind of thing.

    ``kind``: "drive", "bike", "parking", "walk" or "stand"; ``direction`` +1 / -1 (along
    +x / -x) or 0 (static); every object in the lane moves at ``direction * speed``.
    """

    kind: str
    y_min: float
    y_max: float
    direction: int
    speed: float
    side: int    # -1: right of the centre line (y < 0), +1: left

    @property
    def y_center(self) -> float:
        return 0.5 * (self.y_min + self.y_max)

    @property
    def velocity(self) -> float:
        return self.direction * self.speed


@dataclass
class Things:
    """All thing objects of a scene, N rows, world frame.

    ``boxes`` are the GT boxes at t = 0 (extrapolated for objects not alive then); the box
    at time t is ``boxes[:, :2] + velocity * t`` (x wrapped for ``wraps``), alive while
    ``t_birth <= t <= t_death``. Parts: ``part_boxes`` (P, 7) in the owner's box frame
    (origin at the GT box centre, x along its heading), ``part_owner`` (P,) row index.
    """

    boxes: np.ndarray
    velocity: np.ndarray
    cls: np.ndarray
    kitti_type: tuple[str, ...]
    wraps: np.ndarray
    t_birth: np.ndarray
    t_death: np.ndarray
    lane: np.ndarray          # lane index, -1 for crossing pedestrians
    part_boxes: np.ndarray
    part_owner: np.ndarray
    part_reflectivity: np.ndarray

    def __len__(self) -> int:
        return len(self.boxes)


class ThingState(NamedTuple):
    """Things alive at one time: row ``index`` into ``Things`` and their state."""

    index: np.ndarray      # (K,) int
    boxes: np.ndarray      # (K, 7) world
    velocity: np.ndarray   # (K, 2) world
    cls: np.ndarray        # (K,) int32
    instance: np.ndarray   # (K,) int32, >= 1


@dataclass
class Scene:
    """A generated street: static stuff primitives, lanes and things (world frame)."""

    seed: int
    config: SceneConfig
    lanes: tuple[Lane, ...]
    static: Primitives       # world frame, ground_z = 0
    things: Things
    ego_x: float             # ego x at t = 0
    ego_y: float
    ego_speed: float
    static_radius: dict[str, np.ndarray] = field(default_factory=dict)  # BEV radii

    @property
    def length(self) -> float:
        return self.config.length

    def ego_box(self, t: float = 0.0) -> np.ndarray:
        """(7,) ego car footprint box at time t (world, yaw 0)."""
        l, w, h = EGO_SIZE
        return np.array([self.ego_x + self.ego_speed * t, self.ego_y, h / 2, l, w, h, 0.0])

    def thing_state(self, t: float) -> ThingState:
        """Boxes, velocities and instance ids of the things alive at time t (seconds).

        Instance ids: row index + 1, plus ``N * |laps|`` once a wrapping object has gone
        round the street (a respawn), so ids are unique and stable while an object exists.
        """
        th = self.things
        alive = (th.t_birth <= t + _TIME_EPS) & (t - _TIME_EPS <= th.t_death)
        idx = np.flatnonzero(alive)
        b = th.boxes[idx].copy()
        v = th.velocity[idx]
        raw_x = b[:, 0] + v[:, 0] * t
        b[:, 1] += v[:, 1] * t
        lap = np.where(th.wraps[idx], np.floor(raw_x / self.length), 0.0)
        b[:, 0] = raw_x - lap * self.length
        inst = idx + 1 + np.abs(lap).astype(np.int64) * len(th)
        return ThingState(idx, b, v.copy(), th.cls[idx], inst.astype(np.int32))

    def part_boxes(self, state: ThingState, rows=None):
        """World part boxes of ``state``'s things (optionally only ``rows`` of it).

        Returns ``(boxes (P, 7), class, instance, reflectivity)``.
        """
        th = self.things
        rows = np.arange(len(state.index)) if rows is None else np.asarray(rows)
        row_of = np.full(len(th), -1, np.int64)
        row_of[state.index[rows]] = rows
        sel = np.flatnonzero(row_of[th.part_owner] >= 0)
        r = row_of[th.part_owner[sel]]
        lp = th.part_boxes[sel]
        ob = state.boxes[r]
        c, s = np.cos(ob[:, 6]), np.sin(ob[:, 6])
        out = np.empty_like(lp)
        out[:, 0] = ob[:, 0] + c * lp[:, 0] - s * lp[:, 1]
        out[:, 1] = ob[:, 1] + s * lp[:, 0] + c * lp[:, 1]
        out[:, 2] = ob[:, 2] + lp[:, 2]
        out[:, 3:6] = lp[:, 3:6]
        out[:, 6] = wrap_angle(ob[:, 6] + lp[:, 6])
        return (out, state.cls[r].astype(np.int32), state.instance[r].astype(np.int32),
                th.part_reflectivity[sel].copy())


# ----------------------------------------------------------------------------- helpers

def _extents(l: float, w: float, yaw: float) -> tuple[float, float]:
    """Half extents along x and y of a rotated l x w footprint."""
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    return 0.5 * (l * c + w * s), 0.5 * (l * s + w * c)


def _ext(x0, x1, y0, y1, z0, z1) -> list[float]:
    """Axis-aligned part box (local frame, z from the ground) from its extents."""
    return [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2, x1 - x0, y1 - y0, z1 - z0, 0.0]


def street_cross_section(cfg: SceneConfig) -> dict[str, float]:
    """Distances from the centre line: lane edges, curb (road half width), sidewalk."""
    drive = cfg.lanes_per_direction * cfg.lane_width
    bike = drive + cfg.bike_lane_width
    road = bike + cfg.parking_width
    return {"drive": drive, "bike": bike, "road": road,
            "furniture": road + cfg.furniture_width,
            "stand": road + cfg.sidewalk_width - cfg.standing_width,
            "sidewalk": road + cfg.sidewalk_width}


# ------------------------------------------------------------------------ thing shapes

def _sample_size(cls: int, rng, van: bool = False, walking: bool = True):
    if cls == C.CAR:
        l = rng.uniform(3.6, 4.95)
        w = float(np.clip(1.62 + 0.22 * (l - 3.6) + rng.normal(0, 0.05), 1.62, 1.98))
        return l, w, rng.uniform(1.42, 1.68)
    if cls == C.TRUCK:
        if van:
            return rng.uniform(5.0, 6.4), rng.uniform(1.9, 2.1), rng.uniform(2.0, 2.7)
        return rng.uniform(6.6, 9.9), rng.uniform(2.3, 2.53), rng.uniform(2.8, 3.48)
    if cls == C.PEDESTRIAN:
        l = rng.uniform(0.5, 0.64) if walking else rng.uniform(0.4, 0.46)
        return l, rng.uniform(0.52, 0.72), rng.uniform(1.55, 1.92)
    if cls == C.CYCLIST:
        return rng.uniform(1.65, 1.9), rng.uniform(0.56, 0.68), rng.uniform(1.6, 1.85)
    raise ValueError(cls)


def _wheels(xs, w, r, tw):
    ys = (w / 2 - 0.02 - tw / 2, -(w / 2 - 0.02 - tw / 2))
    return [_ext(x - r, x + r, y - tw / 2, y + tw / 2, 0.0, 2 * r) for x in xs for y in ys]


def _car_parts(l, w, h, rng):
    paint = C.sample_reflectivity(rng, C.CAR)
    plate_t = 0.03
    clear, rw = rng.uniform(0.15, 0.24), rng.uniform(0.29, 0.34)
    hb = h * rng.uniform(0.5, 0.58)
    parts, refl = [_ext(-l / 2 + plate_t, l / 2 - plate_t, -w / 2, w / 2, clear, hb)], [paint]
    lc, wc = l * rng.uniform(0.45, 0.58), w - rng.uniform(0.12, 0.25)
    xc = float(np.clip(-rng.uniform(0, 0.08) * l, -l / 2 + plate_t + lc / 2, 0.0))
    parts.append(_ext(xc - lc / 2, xc + lc / 2, -wc / 2, wc / 2, hb, h))
    refl.append(C.sample_reflectivity(rng, material="glass"))
    xs = (l / 2 - rng.uniform(0.75, 0.95), -l / 2 + rng.uniform(0.6, 0.85))
    tyres = _wheels(xs, w, rw, 0.2)
    parts += tyres
    refl += [C.sample_reflectivity(rng, material="tyre")] * len(tyres)
    zp = clear + 0.35 * (hb - clear)
    for sx in (1, -1):
        x_out = sx * l / 2
        parts.append(_ext(min(x_out, x_out - sx * plate_t), max(x_out, x_out - sx * plate_t),
                          -0.26, 0.26, zp - 0.06, zp + 0.06))
        refl.append(C.sample_reflectivity(rng, material="license_plate"))
    return parts, refl


def _truck_parts(l, w, h, rng):
    paint = C.sample_reflectivity(rng, C.TRUCK)
    tyre = C.sample_reflectivity(rng, material="tyre")
    if l < _VAN_MAX_LENGTH:  # van: low body + tall box behind a short hood
        clear, rw = rng.uniform(0.16, 0.24), rng.uniform(0.31, 0.36)
        hb = h * rng.uniform(0.42, 0.5)
        hood = rng.uniform(0.7, 1.0)
        parts = [_ext(-l / 2 + 0.03, l / 2 - 0.03, -w / 2, w / 2, clear, hb),
                 _ext(-l / 2 + 0.03, l / 2 - hood, -w / 2 + 0.03, w / 2 - 0.03, hb, h)]
        refl = [paint, paint]
        xs = (l / 2 - rng.uniform(0.8, 1.0), -l / 2 + rng.uniform(0.8, 1.1))
        tyres = _wheels(xs, w, rw, 0.22)
        for sx in (1, -1):
            zp = clear + 0.3 * (hb - clear)
            x0, x1 = sorted((sx * l / 2, sx * (l / 2 - 0.03)))
            parts.append(_ext(x0, x1, -0.26, 0.26, zp - 0.06, zp + 0.06))
            refl.append(C.sample_reflectivity(rng, material="license_plate"))
    else:  # truck: chassis, cab in front, cargo box behind
        rw = rng.uniform(0.45, 0.52)
        lcab = rng.uniform(1.8, 2.3)
        hcab = min(h, rng.uniform(2.6, 3.1))
        gap = rng.uniform(0.15, 0.3)
        cargo_z0 = rng.uniform(0.95, 1.2)
        parts = [_ext(-l / 2 + 0.1, l / 2 - 0.1, -0.4 * w, 0.4 * w, 0.5, 1.0),
                 _ext(l / 2 - lcab, l / 2, -w / 2 + 0.04, w / 2 - 0.04, 0.45, hcab),
                 _ext(-l / 2, l / 2 - lcab - gap, -w / 2, w / 2, cargo_z0, h)]
        refl = [C.sample_reflectivity(rng, material="tyre") * 2, paint,  # dark underbody
                C.sample_reflectivity(rng, C.TRUCK)]
        rear = -l / 2 + rng.uniform(1.2, 1.8)
        xs = [l / 2 - rng.uniform(1.0, 1.3), rear] + ([rear + 2 * rw + 0.3] if l > 8 else [])
        tyres = _wheels(xs, w, rw, 0.3)
    parts += tyres
    refl += [tyre] * len(tyres)
    return parts, refl


def _person(l, w, h, rng, stride, rider: bool = False, x_off: float = 0.0):
    """Legs, torso, arms and head of a person (standing/walking or riding)."""
    cloth_lo, cloth_hi = C.sample_reflectivity(rng, C.PEDESTRIAN, 2)
    skin = C.sample_reflectivity(rng, material="skin")
    parts, refl = [], []
    if rider:  # on a bike (x_off = seat position): thighs/legs block, torso leaning fwd
        parts.append(_ext(x_off - 0.15, x_off + 0.2, -0.17, 0.17, 0.42, 0.98))
        parts.append(_ext(x_off, x_off + 0.36, -0.2, 0.2, 0.98, h - 0.27))
        parts.append(_ext(x_off + 0.15, x_off + 0.36, -0.09, 0.09, h - 0.25, h))
        return parts, [cloth_lo, cloth_hi, skin]
    ll, lw = rng.uniform(0.15, 0.19), rng.uniform(0.14, 0.17)
    hl = 0.47 * h
    for sy, sx in ((1, 1), (-1, -1)):
        xc = sx * stride
        y0 = sy * 0.03
        parts.append(_ext(xc - ll / 2, xc + ll / 2, *sorted((y0, y0 + sy * lw)), 0.0, hl))
        refl.append(cloth_lo)
    arm = 0.09
    # walking: legs and swinging arms span l; standing: a deeper torso does
    lt = rng.uniform(0.22, 0.3) if stride else l * rng.uniform(0.72, 0.8)
    parts.append(_ext(-lt / 2, lt / 2, -w / 2 + arm + 0.01, w / 2 - arm - 0.01, hl, 0.82 * h))
    refl.append(cloth_hi)
    swing = l / 2 - 0.05 if stride else 0.0
    for sy, sx in ((1, -1), (-1, 1)):
        xc = sx * swing
        parts.append(_ext(xc - 0.05, xc + 0.05, *sorted((sy * w / 2, sy * (w / 2 - arm))),
                          0.5 * h, 0.8 * h))
        refl.append(cloth_hi)
    parts.append(_ext(-0.1, 0.1, -0.08, 0.08, 0.855 * h, h))
    refl.append(skin)
    return parts, refl


def _pedestrian_parts(l, w, h, rng, walking: bool):
    ll_max = 0.19
    stride = rng.uniform(0.6, 1.0) * (l / 2 - ll_max / 2) if walking else 0.0
    return _person(l, w, h, rng, stride)


def _cyclist_parts(l, w, h, rng):
    rw = rng.uniform(0.32, 0.36)
    frame = C.sample_reflectivity(rng, material="bike_frame")
    tyre = C.sample_reflectivity(rng, material="tyre")
    xw = l / 2 - rw
    parts = [_ext(x - rw, x + rw, -0.02, 0.02, 0.0, 2 * rw) for x in (xw, -xw)]
    refl = [tyre, tyre]
    parts.append(_ext(-xw, xw, -0.025, 0.025, 0.5, 0.85))          # frame
    parts.append(_ext(xw - 0.12, xw - 0.06, -w / 2, w / 2, 1.0, 1.05))  # handlebar
    refl += [frame, frame]
    rp, rr = _person(l, w, h, rng, 0.0, rider=True, x_off=-0.2)
    return parts + rp, refl + rr


def _make_thing(cls: int, rng, *, van=False, walking=True):
    """Sample a thing's size and parts: ``(l, w, h, parts (k, 7) local, refl, kitti)``."""
    l, w, h = _sample_size(cls, rng, van=van, walking=walking)
    if cls == C.CAR:
        parts, refl = _car_parts(l, w, h, rng)
    elif cls == C.TRUCK:
        parts, refl = _truck_parts(l, w, h, rng)
    elif cls == C.PEDESTRIAN:
        parts, refl = _pedestrian_parts(l, w, h, rng, walking)
    else:
        parts, refl = _cyclist_parts(l, w, h, rng)
    p = np.asarray(parts, np.float64).reshape(-1, 7)
    p[:, 2] -= h / 2  # local frame origin at the GT box centre
    kitti = C.kitti_type(cls)
    if cls == C.TRUCK:
        kitti = "Van" if l < _VAN_MAX_LENGTH else "Truck"
    return l, w, h, p, np.clip(np.asarray(refl, np.float64), 0.0, 1.0), kitti


# ------------------------------------------------------------------------------ lanes

def _make_lanes(cfg: SceneConfig, rng) -> tuple[list[Lane], int]:
    """All lanes and the index of the ego lane."""
    cs = street_cross_section(cfg)
    lanes, ego = [], -1
    for side in (-1, 1):
        direction = -side  # right-hand traffic
        n = cfg.lanes_per_direction
        for k in range(n):  # k = 0 next to the centre line
            d0, d1 = k * cfg.lane_width, (k + 1) * cfg.lane_width
            is_ego = side == -1 and k == n - 1 - cfg.ego_lane
            speed = cfg.ego_speed if is_ego else rng.uniform(*cfg.vehicle_speed_range)
            if is_ego:
                ego = len(lanes)
            lanes.append(_lane("drive", side, d0, d1, direction, speed))
        if cfg.bike_lane_width > 0:
            lanes.append(_lane("bike", side, cs["drive"], cs["bike"], direction,
                               rng.uniform(*cfg.cyclist_speed_range)))
        if cfg.parking_width > 0:
            lanes.append(_lane("parking", side, cs["bike"], cs["road"], 0, 0.0))
        walk = cs["stand"] - cs["furniture"]
        n_walk = 2 if walk >= 1.8 else 1
        first = int(rng.choice((-1, 1)))
        for k in range(n_walk):
            d0 = cs["furniture"] + k * walk / n_walk
            lanes.append(_lane("walk", side, d0, d0 + walk / n_walk, first * (-1) ** k,
                               rng.uniform(*cfg.walk_speed_range)))
        lanes.append(_lane("stand", side, cs["stand"], cs["sidewalk"], 0, 0.0))
    return lanes, ego


def _lane(kind, side, d0, d1, direction, speed) -> Lane:
    y0, y1 = sorted((side * d0, side * d1))
    return Lane(kind, float(y0), float(y1), int(direction), float(speed), side)


# kind -> (min gap along the lane, typical object length) in metres
_LANE_GAPS = {"drive": (6.0, 5.0), "bike": (4.0, 1.8), "parking": (0.7, 4.6),
              "walk": (1.2, 0.55), "stand": (0.8, 0.5)}


def _lane_density(cfg: SceneConfig, lane: Lane, n_walk: int) -> float:
    if lane.kind == "drive":
        return cfg.moving_per_100m
    if lane.kind == "bike":
        return cfg.cyclists_per_100m
    if lane.kind == "parking":
        return cfg.parked_per_100m
    if lane.kind == "walk":
        return cfg.pedestrians_per_100m * (1 - cfg.standing_fraction) / n_walk
    return cfg.pedestrians_per_100m * cfg.standing_fraction


def _lane_object(cfg, lane: Lane, rng):
    """Sample one object for a lane: (cls, l, w, h, yaw, parts, refl, kitti)."""
    base = 0.0 if lane.direction >= 0 else np.pi
    if lane.kind in ("drive", "parking"):
        frac = cfg.truck_fraction if lane.kind == "drive" else cfg.parked_van_fraction
        is_truck = rng.random() < frac
        van = lane.kind == "parking" or rng.random() < 0.5
        cls = C.TRUCK if is_truck else C.CAR
        l, w, h, parts, refl, kitti = _make_thing(cls, rng, van=van)
        if lane.kind == "parking":
            base = float(rng.choice((0.0, np.pi)))
        noise = np.deg2rad(1.2 if lane.kind == "drive" else 3.0)
    elif lane.kind == "bike":
        cls = C.CYCLIST
        l, w, h, parts, refl, kitti = _make_thing(cls, rng)
        noise = np.deg2rad(2.0)
    else:
        cls = C.PEDESTRIAN
        walking = lane.kind == "walk"
        l, w, h, parts, refl, kitti = _make_thing(cls, rng, walking=walking)
        if walking:
            noise = np.deg2rad(6.0)
        else:
            base, noise = float(rng.choice((0.0, 0.5, 1.0, -0.5))) * np.pi, np.deg2rad(25.0)
    yaw = base + rng.uniform(-noise, noise)
    half = 0.5 * (lane.y_max - lane.y_min) - _LAT_MARGIN
    # too wide when rotated: drop the yaw noise; standing people may also turn sideways
    fallbacks = (yaw, base) + ((base + np.pi / 2,) if lane.kind == "stand" else ())
    for yaw in fallbacks:
        if _extents(l, w, yaw)[1] <= half + 1e-9:
            break
    else:
        raise RuntimeError(f"{C.class_name(cls)} does not fit its {lane.kind} lane")
    return cls, l, w, h, float(wrap_angle(yaw)), parts, refl, kitti


def _lateral(lane: Lane, e_y: float, rng) -> float:
    lo, hi = lane.y_min + _LAT_MARGIN + e_y, lane.y_max - _LAT_MARGIN - e_y
    if lane.kind == "parking":  # hug the curb
        slack = min(0.25, hi - lo)
        return hi - rng.uniform(0, slack) if lane.side > 0 else lo + rng.uniform(0, slack)
    if lane.kind in ("drive", "bike"):
        return float(np.clip(lane.y_center + rng.uniform(-0.2, 0.2), lo, hi))
    return rng.uniform(lo, hi)


def _fill_lane(cfg, lane: Lane, density: float, rng, reserved=None) -> list[dict]:
    """Place objects along a lane seen as a circle of circumference ``length``.

    ``reserved``: (x, half length) kept free (the ego in its lane). Gaps between
    footprints are at least the lane kind's minimum gap, also across the wrap.
    """
    L = cfg.length
    if density <= 0:
        return []
    min_gap, typ = _LANE_GAPS[lane.kind]
    big_p, big = (0.15, (4.0, 15.0)) if lane.kind == "parking" else (0.0, (0.0, 0.0))
    extra = max(100.0 / density - typ - min_gap - big_p * np.mean(big), 0.05)
    if reserved is not None:
        start = reserved[0] + reserved[1] + min_gap + rng.exponential(extra)
        end = reserved[0] - reserved[1] + L
    else:
        start = rng.uniform(0, L)
        end = start + L
    out, pos = [], start
    while True:
        cls, l, w, h, yaw, parts, refl, kitti = _lane_object(cfg, lane, rng)
        e_x, e_y = _extents(l, w, yaw)
        if pos + 2 * e_x + min_gap > end:
            break
        x = pos + e_x
        out.append(dict(cls=cls, box=[x % L, _lateral(lane, e_y, rng), h / 2, l, w, h, yaw],
                        v=(lane.velocity, 0.0), parts=parts, refl=refl, kitti=kitti))
        pos = x + e_x + min_gap + rng.exponential(extra)
        if big_p and rng.random() < big_p:
            pos += rng.uniform(*big)
    return out


# ------------------------------------------------------------------------------ stuff

class _Stuff:
    """Accumulates world-frame static primitives."""

    def __init__(self):
        self.boxes, self.box_c, self.box_r = [], [], []
        self.cyl, self.cyl_c, self.cyl_r = [], [], []
        self.ell, self.ell_c, self.ell_r, self.ell_p = [], [], [], []
        self.ground, self.ground_c, self.ground_r = [], [], []

    def box(self, b, cls, refl):
        self.boxes.append(b), self.box_c.append(cls), self.box_r.append(refl)

    def cylinder(self, c, cls, refl):
        self.cyl.append(c), self.cyl_c.append(cls), self.cyl_r.append(refl)

    def ellipsoid(self, e, refl, porosity):
        self.ell.append(e), self.ell_c.append(C.VEGETATION), self.ell_r.append(refl)
        self.ell_p.append(porosity)

    def region(self, r, cls, refl):
        self.ground.append(r), self.ground_c.append(cls), self.ground_r.append(refl)

    def build(self) -> Primitives:
        def arr(x, cols):
            return np.asarray(x, np.float64).reshape(-1, cols)

        def i32(x):
            return np.asarray(x, np.int32)

        nb, nc, ne = len(self.boxes), len(self.cyl), len(self.ell)
        return Primitives(
            boxes=arr(self.boxes, 7), box_class=i32(self.box_c),
            box_instance=np.zeros(nb, np.int32), box_reflectivity=np.asarray(self.box_r, float),
            cylinders=arr(self.cyl, 5), cylinder_class=i32(self.cyl_c),
            cylinder_instance=np.zeros(nc, np.int32),
            cylinder_reflectivity=np.asarray(self.cyl_r, float),
            ellipsoids=arr(self.ell, 6), ellipsoid_class=i32(self.ell_c),
            ellipsoid_instance=np.zeros(ne, np.int32),
            ellipsoid_reflectivity=np.asarray(self.ell_r, float),
            ellipsoid_porosity=np.asarray(self.ell_p, float),
            ground_z=0.0, ground_regions=arr(self.ground, 4), ground_class=i32(self.ground_c),
            ground_reflectivity=np.asarray(self.ground_r, float),
            default_ground_class=C.TERRAIN, default_ground_reflectivity=0.4)


def _ground(cfg: SceneConfig, st: _Stuff, rng) -> None:
    """Non-overlapping ground rectangles: terrain, sidewalks, asphalt and lane paint."""
    cs = street_cross_section(cfg)
    x0, x1 = -cfg.ground_margin, cfg.length + cfg.ground_margin
    Y = max(cfg.terrain_extent, cs["sidewalk"] + 1.0)
    for side in (-1, 1):
        st.region([x0, x1, *sorted((side * cs["sidewalk"], side * Y))], C.TERRAIN,
                  C.sample_reflectivity(rng, C.TERRAIN))
        st.region([x0, x1, *sorted((side * cs["road"], side * cs["sidewalk"]))], C.SIDEWALK,
                  C.sample_reflectivity(rng, C.SIDEWALK))
    # Lane lines: (y centre, width, dashed). Dashed between lanes, solid at the bike lane.
    lines = [(k * cfg.lane_width * s, 0.15, True)
             for k in range(cfg.lanes_per_direction) for s in ((1,) if k == 0 else (-1, 1))]
    if cfg.bike_lane_width > 0 or cfg.parking_width > 0:
        lines += [(s * (cs["drive"] + 0.1), 0.2, False) for s in (-1, 1)]
    lines.sort()
    asphalt = C.sample_reflectivity(rng, C.ROAD)
    paint = C.sample_reflectivity(rng, material="lane_paint")
    y = -cs["road"]
    period = cfg.dash_length + cfg.dash_gap
    for yc, wd, dashed in lines:
        st.region([x0, x1, y, yc - wd / 2], C.ROAD, asphalt + rng.uniform(-0.02, 0.02))
        if dashed:
            xs = np.arange(x0, x1, period)
            for xa in xs:
                xb = min(xa + cfg.dash_length, x1)
                st.region([xa, xb, yc - wd / 2, yc + wd / 2], C.ROAD, paint)
                if xb < x1:
                    st.region([xb, min(xa + period, x1), yc - wd / 2, yc + wd / 2], C.ROAD,
                              asphalt)
        else:
            st.region([x0, x1, yc - wd / 2, yc + wd / 2], C.ROAD, paint)
        y = yc + wd / 2
    st.region([x0, x1, y, cs["road"]], C.ROAD, asphalt + rng.uniform(-0.02, 0.02))


def _tree(st: _Stuff, x, y, r, zb, rng, obstacles):
    """Trunk cylinder + 1-3 porous crown ellipsoids (all within radius ~r of the trunk)."""
    rz = rng.uniform(1.2, 2.6) * min(1.0, r / 2.0 + 0.3)
    trunk_r = float(np.clip(0.07 * r + rng.uniform(0.0, 0.08), 0.1, 0.3))
    st.cylinder([x, y, 0.0, zb + 0.6 * rz, trunk_r], C.TRUNK, C.sample_reflectivity(rng, C.TRUNK))
    obstacles.append((x, y, trunk_r))
    refl = C.sample_reflectivity(rng, C.VEGETATION)
    por = rng.uniform(0.3, 0.6)
    st.ellipsoid([x, y, zb + rz, r * rng.uniform(0.85, 1.0), r * rng.uniform(0.85, 1.0), rz],
                 refl, por)
    for _ in range(int(rng.integers(0, 3))):
        s = rng.uniform(0.45, 0.65)
        off = (1 - s) * r * rng.uniform(0.3, 0.9)
        a = rng.uniform(0, 2 * np.pi)
        st.ellipsoid([x + off * np.cos(a), y + off * np.sin(a),
                      zb + rz + rng.uniform(-0.1, 0.5) * rz, s * r, s * r, s * rz],
                     refl + rng.uniform(-0.03, 0.03), por)


_HEDGE_MIN_SETBACK = 3.5   # a hedge (<= 1.6 m deep, 0.3 m off the sidewalk) fits in front


def _hedged(cfg: SceneConfig, rng) -> bool:
    """Whether the next gap / front yard gets a hedge (no draw when ``hedge_prob`` is 0,
    so configurations without hedges keep their random streams)."""
    return cfg.hedge_prob > 0 and rng.random() < cfg.hedge_prob


def _hedge(st: _Stuff, x0: float, x1: float, side: int, sw: float, rng) -> float:
    """A hedge along x in [x0, x1] just behind the sidewalk edge ``sw``: a row of dense,
    overlapping vegetation ellipsoids. Returns the distance of its far side from the
    centre line (``sw``, and no hedge, for a stretch shorter than 1 m)."""
    if x1 - x0 < 1.0:
        return sw
    ry, rz = rng.uniform(0.4, 0.8), rng.uniform(0.6, 1.1)
    d = sw + 0.3 + ry
    refl, por = C.sample_reflectivity(rng, C.VEGETATION), rng.uniform(0.1, 0.3)
    rx = min(1.1, 0.5 * (x1 - x0))                  # half length of one ellipsoid
    n = int(np.ceil((x1 - x0 - 2 * rx) / 1.4)) + 1  # centres <= 1.4 m apart: they overlap
    for xc in np.linspace(x0 + rx, x1 - rx, n):
        st.ellipsoid([xc, side * d, rz * rng.uniform(0.85, 1.0), rx, ry, rz],
                     refl + rng.uniform(-0.02, 0.02), por)
    return d + ry


def _scenery(cfg: SceneConfig, st: _Stuff, rng) -> list[tuple[float, float, float]]:
    """Buildings, fences, vegetation, poles and signs; returns low obstacle circles."""
    cs = street_cross_section(cfg)
    L = cfg.length
    obstacles: list[tuple[float, float, float]] = []
    for side in (-1, 1):
        sw = cs["sidewalk"]
        fronts = []   # (x0, x1, front distance) of buildings
        green = []    # terrain areas (x0, x1, d0, d1, has building behind)
        x = rng.uniform(-5.0, 2.0)
        while x < L:
            if rng.random() < cfg.building_gap_prob:
                gap = rng.uniform(*cfg.building_gap_range)
                fence_d = None
                if _hedged(cfg, rng):   # draws nothing unless hedge_prob > 0
                    fence_d = _hedge(st, x + 0.3, x + gap - 0.3, side, sw, rng)
                elif rng.random() < cfg.fence_prob:
                    fence_d = sw + rng.uniform(0.05, 0.5)
                    t, fh = rng.uniform(0.04, 0.08), rng.uniform(1.0, 1.8)
                    st.box([x + gap / 2, side * fence_d, fh / 2, gap - 0.4, t, fh, 0.0],
                           C.FENCE, C.sample_reflectivity(rng, C.FENCE))
                green.append((x + 0.3, x + gap - 0.3, (fence_d or sw) + 0.2, sw + 12.0, False))
                x += gap
            width, depth = rng.uniform(*cfg.building_width_range), rng.uniform(8.0, 20.0)
            height = (rng.uniform(*cfg.building_height_range)
                      if rng.random() < 1.0 - cfg.tall_building_prob else rng.uniform(14.0, 30.0))
            setback = (0.0 if rng.random() < cfg.flush_building_prob
                       else rng.uniform(cfg.setback_min, cfg.setback_max))
            front = sw + setback
            refl = C.sample_reflectivity(rng, C.BUILDING)
            st.box([x + width / 2, side * (front + depth / 2), height / 2, width, depth,
                    height, 0.0], C.BUILDING, refl)
            if rng.random() < 0.3:  # roof structure
                rl, rw_, rh = width * rng.uniform(0.3, 0.7), depth * rng.uniform(0.3, 0.7), \
                    rng.uniform(2.0, 4.0)
                cx = x + width / 2 + rng.uniform(-1, 1) * (width - rl) / 2
                cy = front + depth / 2 + rng.uniform(-1, 1) * (depth - rw_) / 2
                st.box([cx, side * cy, height + rh / 2, rl, rw_, rh, 0.0], C.BUILDING,
                       refl + rng.uniform(-0.05, 0.05))
            fronts.append((x, x + width, front))
            if setback > 0.8:
                d0 = sw + 0.2
                if setback > _HEDGE_MIN_SETBACK and _hedged(cfg, rng):
                    d0 = _hedge(st, x + 0.2, x + width - 0.2, side, sw, rng) + 0.2
                elif setback > 1.5 and rng.random() < 0.3:
                    fh = rng.uniform(0.8, 1.4)
                    st.box([x + width / 2, side * (sw + 0.1), fh / 2, width - 0.3, 0.05, fh,
                            0.0], C.FENCE, C.sample_reflectivity(rng, C.FENCE))
                    d0 = sw + 0.35
                green.append((x + 0.2, x + width - 0.2, d0, front - 0.2, True))
            x += width + rng.uniform(0.3, 1.0)

        def front_at(xa, xb):
            f = [fr for (a, b, fr) in fronts if a < xb and b > xa]
            return min(f) if f else np.inf

        # curb-side furniture: street lights, signs, street trees (x clearances)
        d_f = cs["road"] + cfg.furniture_width / 2
        taken: list[tuple[float, float]] = []   # (x, clearance radius)

        def free(xc, rad):
            return 0 < xc < L and all(abs(xc - xo) >= rad + ro for xo, ro in taken)

        offset = rng.uniform(0, cfg.street_light_spacing)
        for xl in np.arange(offset, L, cfg.street_light_spacing):
            xl = xl + rng.uniform(-2, 2)
            if not free(xl, 1.5):
                continue
            taken.append((xl, 1.5))
            r, hp = rng.uniform(0.09, 0.13), rng.uniform(7.0, 9.0)
            yl = side * d_f
            refl = C.sample_reflectivity(rng, C.POLE)
            st.cylinder([xl, yl, 0.0, hp, r], C.POLE, refl)
            arm = rng.uniform(1.2, 2.0)
            st.box([xl, side * (d_f - arm / 2), hp - 0.05, 0.1, arm, 0.1, 0.0], C.POLE, refl)
            st.box([xl, side * (d_f - arm + 0.2), hp - 0.2, 0.35, 0.6, 0.15, 0.0], C.POLE,
                   refl)
            obstacles.append((xl, yl, r))
        for _ in range(rng.poisson(cfg.signs_per_100m * L / 100)):
            xs = rng.uniform(0, L)
            if not free(xs, 1.0):
                continue
            taken.append((xs, 1.0))
            r, hp = rng.uniform(0.03, 0.05), rng.uniform(2.2, 3.0)
            ys = side * d_f
            st.cylinder([xs, ys, 0.0, hp, r], C.POLE, C.sample_reflectivity(rng, C.POLE))
            obstacles.append((xs, ys, r))
            xsign = xs + side * (r + 0.03)  # faces the traffic approaching on this side
            z_top = hp
            for _k in range(1 + int(rng.random() < 0.3)):
                sw_, sh = rng.uniform(0.5, 0.8), rng.uniform(0.5, 0.8)
                if z_top - sh < 1.2:  # keep signs above head-ish height
                    break
                st.box([xsign, ys, z_top - sh / 2, 0.04, sw_, sh, 0.0], C.TRAFFIC_SIGN,
                       C.sample_reflectivity(rng, C.TRAFFIC_SIGN))
                obstacles.append((xsign, ys, 0.5 * np.hypot(0.04, sw_)))
                z_top -= sh + 0.1
        reach_road = d_f - cs["drive"] - 0.2  # crowns may overhang parking / bike lanes
        for _ in range(rng.poisson(cfg.street_trees_per_100m * L / 100)):
            xt = rng.uniform(0, L)
            if not free(xt, 2.5):
                continue
            r = rng.uniform(1.5, 3.2)
            r = min(r, reach_road, front_at(xt - r, xt + r) - d_f - 0.3)
            if r < 1.0:
                continue
            taken.append((xt, 2.5))
            _tree(st, xt, side * d_f, r, rng.uniform(3.0, 4.5), rng, obstacles)
        # yard trees and bushes on terrain
        areas = [g for g in green if g[1] - g[0] > 1.0 and g[3] - g[2] > 1.0]
        if not areas:
            continue
        weights = np.array([(g[1] - g[0]) * (g[3] - g[2]) for g in areas])
        weights /= weights.sum()
        for _ in range(rng.poisson(cfg.yard_trees_per_100m * L / 100)):
            x0, x1, d0, d1, _b = areas[rng.choice(len(areas), p=weights)]
            r = min(rng.uniform(1.5, 3.5), (x1 - x0) / 2 - 0.2)
            dt = rng.uniform(d0 + 0.5, max(d0 + 0.5, min(d1 - 0.5, d0 + 8)))
            r = min(r, d1 - dt - 0.2 if _b else r, front_at(x0, x1) - dt - 0.3)
            if r < 1.0:
                continue
            xt = rng.uniform(x0 + r, x1 - r)
            _tree(st, xt, side * dt, r, rng.uniform(2.5, 4.0), rng, obstacles)
        for _ in range(rng.poisson(cfg.bushes_per_100m * L / 100)):
            x0, x1, d0, d1, _b = areas[rng.choice(len(areas), p=weights)]
            rx, ry = rng.uniform(0.4, 1.3, 2)
            rx, ry = min(rx, (x1 - x0) / 2 - 0.05), min(ry, (d1 - d0) / 2 - 0.05)
            if min(rx, ry) < 0.25:
                continue
            rz = rng.uniform(0.35, 0.9)
            db = rng.uniform(d0 + ry, d1 - ry)
            st.ellipsoid([rng.uniform(x0 + rx, x1 - rx), side * db, rz * rng.uniform(0.5, 0.8),
                          rx, ry, rz], C.sample_reflectivity(rng, C.VEGETATION),
                         rng.uniform(0.2, 0.45))
    return obstacles


# --------------------------------------------------------------------------- crossing

def _positions(boxes, vel, wraps, birth, death, L, times):
    """(T, N) x, y and alive mask of objects at ``times``."""
    raw = boxes[None, :, 0] + vel[None, :, 0] * times[:, None]
    x = np.where(wraps[None], raw % L, raw)
    y = boxes[None, :, 1] + vel[None, :, 1] * times[:, None]
    tt = times[:, None]
    alive = (birth[None] <= tt + _TIME_EPS) & (tt - _TIME_EPS <= death[None])
    return x, y, alive


def _aabb_half(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half extents of the axis-aligned boxes around rotated BEV footprints."""
    c, s = np.abs(np.cos(b[:, 6])), np.abs(np.sin(b[:, 6]))
    return 0.5 * (b[:, 3] * c + b[:, 4] * s), 0.5 * (b[:, 3] * s + b[:, 4] * c)


def _crossing(cfg: SceneConfig, objs: list[dict], ego, obstacles, rng, dt: float):
    """Pedestrians crossing the street, kept only if clear of everything at every frame.

    Clearance uses the axis-aligned boxes around the rotated footprints (they contain the
    footprints, so a clear AABB test guarantees no BEV overlap) plus a margin.
    """
    cs = street_cross_section(cfg)
    L = cfg.length
    ego_x, ego_y, ego_v = ego
    ego_hx, ego_hy = EGO_SIZE[0] / 2, EGO_SIZE[1] / 2
    obs = np.asarray(obstacles, float).reshape(-1, 3)
    margin = 0.3
    out = []
    for _ in range(cfg.crossing_pedestrians):
        every = objs + out
        b = np.array([o["box"] for o in every], float).reshape(-1, 7)
        v = np.array([o["v"] for o in every], float).reshape(-1, 2)
        wr = np.array([o["wraps"] for o in every], bool)
        tb = np.array([o.get("t_birth", -np.inf) for o in every], float)
        td = np.array([o.get("t_death", np.inf) for o in every], float)
        hx, hy = _aabb_half(b)
        for _attempt in range(200):
            l, w, h, parts, refl, kitti = _make_thing(C.PEDESTRIAN, rng, walking=True)
            s = int(rng.choice((-1, 1)))  # start side
            walk_lo, walk_hi = cs["furniture"] + 0.4, cs["sidewalk"] - 0.4
            y0 = s * rng.uniform(walk_lo, walk_hi)
            y1 = -s * rng.uniform(walk_lo, walk_hi)
            speed = rng.uniform(1.2, 1.9)
            yaw = float(wrap_angle(-s * np.pi / 2 + rng.uniform(-0.08, 0.08)))
            x_lo = max(5.0, ego_x - 50.0)
            x_hi = min(L - 5.0, ego_x + ego_v * cfg.duration + 60.0)
            if x_hi <= x_lo:
                break
            xc = rng.uniform(x_lo, x_hi)
            span = abs(y1 - y0) / speed
            k0 = int(np.floor(rng.uniform(-0.5 * span, max(cfg.duration - 0.2 * span, 0.0)) / dt))
            times = np.arange(k0, k0 + int(np.floor(span / dt)) + 1) * dt
            vy = -s * speed
            py = y0 + vy * (times - times[0])
            px_h, py_h = _extents(l, w, yaw)
            x, y, alive = _positions(b, v, wr, tb, td, L, times)
            hit = ((np.abs(x - xc) < hx + px_h + margin)
                   & (np.abs(y - py[:, None]) < hy + py_h + margin) & alive)
            ex = ego_x + ego_v * times
            hit_ego = ((np.abs(ex - xc) < ego_hx + px_h + margin)
                       & (np.abs(ego_y - py) < ego_hy + py_h + margin))
            if hit.any() or hit_ego.any():
                continue
            if len(obs):
                od2 = (obs[None, :, 0] - xc) ** 2 + (obs[None, :, 1] - py[:, None]) ** 2
                if (od2 < (obs[None, :, 2] + np.hypot(px_h, py_h) + 0.2) ** 2).any():
                    continue
            out.append(dict(cls=C.PEDESTRIAN, box=[xc, y0 - vy * times[0], h / 2, l, w, h, yaw],
                            v=(0.0, vy), parts=parts, refl=refl, kitti=kitti, wraps=False,
                            t_birth=times[0], t_death=times[-1], lane=-1))
            break
    return out


# ----------------------------------------------------------------------------- public

def generate_scene(seed: int, config: SceneConfig | None = None) -> Scene:
    """Generate a street scene deterministically from ``seed`` (numpy default_rng)."""
    cfg = config or SceneConfig()
    cfg.validate()
    rng = np.random.default_rng(seed)
    ego_x = cfg.length / 2 if cfg.ego_x is None else float(cfg.ego_x)
    lanes, ego_lane = _make_lanes(cfg, rng)
    ego_y = lanes[ego_lane].y_center
    st = _Stuff()
    _ground(cfg, st, rng)
    obstacles = _scenery(cfg, st, rng)
    n_walk = sum(1 for ln in lanes if ln.kind == "walk" and ln.side == -1)
    objs = []
    for i, lane in enumerate(lanes):
        reserved = (ego_x % cfg.length, EGO_SIZE[0] / 2) if i == ego_lane else None
        for o in _fill_lane(cfg, lane, _lane_density(cfg, lane, n_walk), rng, reserved):
            o["lane"] = i
            o["wraps"] = lane.direction != 0
            objs.append(o)
    objs += _crossing(cfg, objs, (ego_x, ego_y, cfg.ego_speed), obstacles, rng, cfg.dt)

    n = len(objs)
    parts = [o["parts"] for o in objs]
    things = Things(
        boxes=np.array([o["box"] for o in objs], float).reshape(n, 7),
        velocity=np.array([o["v"] for o in objs], float).reshape(n, 2),
        cls=np.array([o["cls"] for o in objs], np.int32),
        kitti_type=tuple(o["kitti"] for o in objs),
        wraps=np.array([o["wraps"] for o in objs], bool),
        t_birth=np.array([o.get("t_birth", -np.inf) for o in objs], float),
        t_death=np.array([o.get("t_death", np.inf) for o in objs], float),
        lane=np.array([o["lane"] for o in objs], np.int32),
        part_boxes=np.concatenate(parts) if n else np.zeros((0, 7)),
        part_owner=np.repeat(np.arange(n), [len(p) for p in parts]).astype(np.int64),
        part_reflectivity=np.concatenate([o["refl"] for o in objs]) if n else np.zeros(0),
    )
    static = st.build()
    radius = {
        "boxes": 0.5 * np.hypot(static.boxes[:, 3], static.boxes[:, 4]),
        "cylinders": static.cylinders[:, 4].copy(),
        "ellipsoids": np.maximum(static.ellipsoids[:, 3], static.ellipsoids[:, 4]),
    }
    return Scene(seed=seed, config=cfg, lanes=tuple(lanes), static=static, things=things,
                 ego_x=ego_x, ego_y=ego_y, ego_speed=cfg.ego_speed, static_radius=radius)
