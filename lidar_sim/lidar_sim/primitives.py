"""The geometry the ray caster sees: arrays of primitives in the SENSOR frame.

A scene (``scene.py``) turns its world into these arrays for each frame (the ego pose
applied); the ray caster (``raycast.py``) intersects beams with them. Every primitive
carries the ground truth a hit inherits: semantic class id (``classes.py``), instance id
(0 = none, e.g. stuff classes like road or building) and surface reflectivity in [0, 1].
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _empty(cols: int) -> np.ndarray:
    return np.zeros((0, cols), dtype=np.float64)


@dataclass
class Primitives:
    """All arrays are float64 unless noted; N* rows, one per primitive.

    - ``boxes`` (Nb, 7): oriented boxes x, y, z (centre), l, w, h, yaw (about +z).
    - ``cylinders`` (Nc, 5): vertical cylinders x, y, z_min, z_max, radius (poles, trunks).
    - ``ellipsoids`` (Ne, 6): axis-aligned ellipsoids x, y, z, rx, ry, rz (tree crowns,
      bushes); ``ellipsoid_porosity`` (Ne,) in [0, 1): probability that a beam passes
      through without a return (vegetation is porous).
    - ``ground_z``: height of the ground plane z = ground_z (sensor frame, usually
      -mount height); ``ground_class`` (Ng,) and ``ground_regions`` (Ng, 4) x_min, x_max,
      y_min, y_max, yaw-free rectangles giving the class and reflectivity of the ground
      (road, sidewalk, terrain); points outside every region get ``default_ground_class``.
    - ``*_class`` int32 semantic class, ``*_instance`` int32 instance id,
      ``*_reflectivity`` float64 in [0, 1], one per primitive of that kind.
    """

    boxes: np.ndarray = field(default_factory=lambda: _empty(7))
    box_class: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    box_instance: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    box_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))

    cylinders: np.ndarray = field(default_factory=lambda: _empty(5))
    cylinder_class: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    cylinder_instance: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    cylinder_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))

    ellipsoids: np.ndarray = field(default_factory=lambda: _empty(6))
    ellipsoid_class: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    ellipsoid_instance: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    ellipsoid_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ellipsoid_porosity: np.ndarray = field(default_factory=lambda: np.zeros(0))

    ground_z: float = -1.73
    ground_regions: np.ndarray = field(default_factory=lambda: _empty(4))
    ground_class: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    ground_reflectivity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    default_ground_class: int = 0
    default_ground_reflectivity: float = 0.2
