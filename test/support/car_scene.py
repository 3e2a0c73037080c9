"""A lone simulated car on flat ground, scanned by an HDL-64 (detector / proposal tests)."""
import numpy as np
from lidar_sim.primitives import Primitives
from lidar_sim.sensor import hdl64, scan

GROUND_Z = -1.73


def car_scene(x, y, yaw, l=4.5, w=1.8, h=1.5, seed=0, clutter=True):
    """A lone car (body, glass cabin, tyres; instance 1) on flat ground, optionally with a
    pole and a bush, scanned by an HDL-64. Returns the scan and the car's GT box."""
    parts = np.array([  # local x, y, bottom z, l, w, h
        [0, 0, 0.2, l - 0.06, w, 0.65], [-0.1 * l, 0, 0.85, 0.5 * l, w - 0.2, h - 0.85],
        *[[sx * (l / 2 - 0.8), sy * (w / 2 - 0.12), 0.0, 0.64, 0.2, 0.64]
          for sx in (1, -1) for sy in (1, -1)]])
    c, s = np.cos(yaw), np.sin(yaw)
    boxes = np.c_[x + c * parts[:, 0] - s * parts[:, 1], y + s * parts[:, 0] + c * parts[:, 1],
                  GROUND_Z + parts[:, 2] + parts[:, 5] / 2, parts[:, 3:6], np.full(len(parts), yaw)]
    kw = {}
    if clutter:
        kw = dict(cylinders=np.array([[-6.0, 9.0, GROUND_Z, GROUND_Z + 6.0, 0.08]]),
                  cylinder_class=np.array([8], np.int32), cylinder_instance=np.zeros(1, np.int32),
                  cylinder_reflectivity=np.array([0.4]),
                  ellipsoids=np.array([[-4.0, -12.0, GROUND_Z + 0.5, 1.0, 0.8, 0.7]]),
                  ellipsoid_class=np.array([6], np.int32), ellipsoid_instance=np.zeros(1, np.int32),
                  ellipsoid_reflectivity=np.array([0.45]), ellipsoid_porosity=np.array([0.3]))
    prims = Primitives(boxes=boxes, box_class=np.full(len(parts), 10, np.int32),
                       box_instance=np.ones(len(parts), np.int32),
                       box_reflectivity=np.r_[0.5, 0.1, [0.05] * 4], ground_z=GROUND_Z, **kw)
    gt = np.array([[x, y, GROUND_Z + h / 2, l, w, h, yaw]])
    return scan(prims, hdl64(), np.random.default_rng(seed)), gt
