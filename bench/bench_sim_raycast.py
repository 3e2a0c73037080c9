"""Lidar simulator ray-casting figure: ``sim.scan_ms`` = one HDL-64 (64 x 2048 beams)
``scan()`` of a street scene with ~300 primitives (target <= 200 ms on one core)."""
from __future__ import annotations

import numpy as np

from lidar_sim.primitives import Primitives
from lidar_sim.sensor import hdl64, scan

# plain SemanticKITTI-like class ids (the bench does not depend on classes.py)
CAR, BICYCLE, PERSON, ROAD, SIDEWALK, BUILDING, VEGETATION, TRUNK, TERRAIN, POLE, SIGN = (
    10, 11, 30, 40, 48, 50, 70, 71, 72, 80, 81)


def street_scene(seed: int = 0, ground_z: float = -1.73) -> Primitives:
    """Straight street along x (road |y| < 5 m, sidewalks to 8 m), buildings both sides,
    40 cars (body + cabin, every 4th a van with a cargo box), 8 bicycles, 12 pedestrians,
    30 trees (trunk + porous crown), 20 bushes, 40 poles with signs: ~310 primitives."""
    rng = np.random.default_rng(seed)
    boxes, bcls, binst, brefl = [], [], [], []
    inst = 1

    def box(x, y, z, l, w, h, yaw, c, i, r):
        boxes.append([x, y, z, l, w, h, yaw])
        bcls.append(c)
        binst.append(i)
        brefl.append(r)

    for side in (-1, 1):  # buildings: stuff class, no instance
        x = -110.0
        while x < 110.0:
            length = rng.uniform(14, 26)
            depth, height = rng.uniform(10, 16), rng.uniform(8, 25)
            front = rng.uniform(9.0, 11.0)
            box(x + length / 2, side * (front + depth / 2), ground_z + height / 2, length,
                depth, height, 0.0, BUILDING, 0, rng.uniform(0.2, 0.5))
            x += length + rng.uniform(0.5, 4.0)
    lanes = (-3.8, -1.75, 1.75, 3.8)  # parked, driving, driving, parked
    for _ in range(40):
        y = lanes[rng.integers(4)] + rng.normal(0, 0.15)
        x = rng.uniform(-70, 70)
        if abs(y) < 3 and abs(x) < 8:
            x += np.sign(x + 1e-9) * 10  # keep clear of the ego car
        yaw = rng.normal(0, 0.05) + (np.pi if y < 0 else 0.0)
        c, s = np.cos(yaw), np.sin(yaw)
        refl = rng.uniform(0.05, 0.8)
        box(x, y, ground_z + 0.75, 4.5, 1.8, 1.0, yaw, CAR, inst, refl)
        box(x - 0.3 * c, y - 0.3 * s, ground_z + 1.5, 2.4, 1.6, 0.55, yaw, CAR, inst, refl)
        if inst % 4 == 0:  # every 4th is a van: a tall cargo box behind the cabin
            box(x - 1.2 * c, y - 1.2 * s, ground_z + 1.6, 2.0, 1.8, 1.4, yaw, CAR, inst, refl)
        inst += 1
    for _ in range(8):  # parked bicycles: frame + rider-less handlebar block
        x, y = rng.uniform(-60, 60), rng.choice([-1, 1]) * rng.uniform(5.2, 5.5)
        box(x, y, ground_z + 0.45, 1.7, 0.1, 0.9, 0.0, BICYCLE, inst, 0.4)
        box(x + 0.6, y, ground_z + 1.0, 0.1, 0.6, 0.1, 0.0, BICYCLE, inst, 0.4)
        inst += 1
    for _ in range(12):
        x, y = rng.uniform(-50, 50), rng.choice([-1, 1]) * rng.uniform(5.5, 7.5)
        box(x, y, ground_z + 0.45, 0.35, 0.4, 0.9, rng.uniform(-np.pi, np.pi), PERSON, inst, 0.3)
        box(x, y, ground_z + 1.3, 0.5, 0.45, 0.8, rng.uniform(-np.pi, np.pi), PERSON, inst, 0.3)
        inst += 1
    cyl, ccls, cinst, crefl = [], [], [], []
    ell, ecls, einst, erefl, epor = [], [], [], [], []
    for _ in range(30):
        x, y = rng.uniform(-90, 90), rng.choice([-1, 1]) * rng.uniform(6.5, 7.5)
        hgt = rng.uniform(2.5, 4.0)
        cyl.append([x, y, ground_z, ground_z + hgt, rng.uniform(0.15, 0.3)])
        ccls.append(TRUNK)
        cinst.append(inst)
        crefl.append(0.25)
        rxy = rng.uniform(1.5, 2.8)
        ell.append([x, y, ground_z + hgt + 1.5, rxy, rxy, rng.uniform(1.8, 3.0)])
        ecls.append(VEGETATION)
        einst.append(0)
        erefl.append(0.35)
        epor.append(rng.uniform(0.2, 0.5))
        inst += 1
    for _ in range(20):  # bushes on the terrain strip, no instance
        x, y = rng.uniform(-90, 90), rng.choice([-1, 1]) * rng.uniform(8.3, 8.8)
        ell.append([x, y, ground_z + 0.5, rng.uniform(0.6, 1.5), 0.5, rng.uniform(0.5, 0.9)])
        ecls.append(VEGETATION)
        einst.append(0)
        erefl.append(0.4)
        epor.append(0.1)
    for _ in range(40):
        x, y = rng.uniform(-90, 90), rng.choice([-1, 1]) * 5.6
        cyl.append([x, y, ground_z, ground_z + 6.0, 0.1])
        ccls.append(POLE)
        cinst.append(inst)
        crefl.append(0.5)
        box(x, y, ground_z + 2.6, 0.05, 0.8, 0.8, 0.0, SIGN, inst, 0.9)
        inst += 1
    def i32(v):
        return np.asarray(v, np.int32)
    return Primitives(
        boxes=np.asarray(boxes), box_class=i32(bcls), box_instance=i32(binst),
        box_reflectivity=np.asarray(brefl),
        cylinders=np.asarray(cyl), cylinder_class=i32(ccls), cylinder_instance=i32(cinst),
        cylinder_reflectivity=np.asarray(crefl),
        ellipsoids=np.asarray(ell), ellipsoid_class=i32(ecls), ellipsoid_instance=i32(einst),
        ellipsoid_reflectivity=np.asarray(erefl), ellipsoid_porosity=np.asarray(epor),
        ground_z=ground_z,
        ground_regions=np.array([[-1e3, 1e3, -5, 5], [-1e3, 1e3, -8, 8]], np.float64),
        ground_class=i32([ROAD, SIDEWALK]), ground_reflectivity=np.array([0.15, 0.3]),
        default_ground_class=TERRAIN, default_ground_reflectivity=0.25)


def figures():
    prims = street_scene()
    cfg = hdl64()
    rng = np.random.default_rng(0)
    yield "sim.scan_ms", lambda: scan(prims, cfg, rng)


if __name__ == "__main__":
    p = street_scene()
    n = len(p.boxes) + len(p.cylinders) + len(p.ellipsoids)
    s = scan(p, hdl64(), np.random.default_rng(0))
    print(f"{n} primitives, {len(s)} points")
