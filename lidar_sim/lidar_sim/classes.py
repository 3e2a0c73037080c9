"""The simulator's class table: the single place that defines semantic classes.

Our class ids are contiguous (``0 .. NUM_CLASSES - 1``, 0 = unlabeled). Each class is
written to disk as its SemanticKITTI label id (``semantickitti_id``); "things" (classes
with instances and 3D boxes) also carry the KITTI object-label type they are written as.
Reflectivities are typical lidar surface reflectivities in [0, 1] the scene samples from.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "ClassInfo", "CLASSES", "NUM_CLASSES", "CLASS_NAMES", "THING_CLASS_IDS", "STUFF_CLASS_IDS",
    "UNLABELED", "ROAD", "SIDEWALK", "TERRAIN", "BUILDING", "FENCE", "VEGETATION", "TRUNK",
    "POLE", "TRAFFIC_SIGN", "CAR", "TRUCK", "PEDESTRIAN", "CYCLIST",
    "MATERIAL_REFLECTIVITY", "SEMANTICKITTI_LABELS", "SEMANTICKITTI_COLORS_BGR",
    "TO_SEMANTICKITTI", "FROM_SEMANTICKITTI",
    "class_id", "class_name", "is_thing", "kitti_type", "to_semantickitti",
    "from_semantickitti", "colors_rgb", "sample_reflectivity", "semantickitti_class_map",
]


@dataclass(frozen=True)
class ClassInfo:
    """One row of the class table."""

    id: int                       # our contiguous id
    name: str
    semantickitti_id: int         # SemanticKITTI raw label it is written as
    rgb: tuple[int, int, int]     # plot colour
    is_thing: bool                # has instances and 3D boxes
    kitti_type: str | None        # KITTI object-label type (things only)
    reflectivity: tuple[float, float]  # typical surface reflectivity range [lo, hi]


# The full SemanticKITTI label set (semantic-kitti.yaml): raw id -> name, colour (BGR).
SEMANTICKITTI_LABELS: dict[int, str] = {
    0: "unlabeled", 1: "outlier", 10: "car", 11: "bicycle", 13: "bus", 15: "motorcycle",
    16: "on-rails", 18: "truck", 20: "other-vehicle", 30: "person", 31: "bicyclist",
    32: "motorcyclist", 40: "road", 44: "parking", 48: "sidewalk", 49: "other-ground",
    50: "building", 51: "fence", 52: "other-structure", 60: "lane-marking", 70: "vegetation",
    71: "trunk", 72: "terrain", 80: "pole", 81: "traffic-sign", 99: "other-object",
    252: "moving-car", 253: "moving-bicyclist", 254: "moving-person",
    255: "moving-motorcyclist", 256: "moving-on-rails", 257: "moving-bus",
    258: "moving-truck", 259: "moving-other-vehicle",
}
SEMANTICKITTI_COLORS_BGR: dict[int, tuple[int, int, int]] = {
    0: (0, 0, 0), 1: (0, 0, 255), 10: (245, 150, 100), 11: (245, 230, 100),
    13: (250, 80, 100), 15: (150, 60, 30), 16: (255, 0, 0), 18: (180, 30, 80),
    20: (255, 0, 0), 30: (30, 30, 255), 31: (200, 40, 255), 32: (90, 30, 150),
    40: (255, 0, 255), 44: (255, 150, 255), 48: (75, 0, 75), 49: (75, 0, 175),
    50: (0, 200, 255), 51: (50, 120, 255), 52: (0, 150, 255), 60: (170, 255, 150),
    70: (0, 175, 0), 71: (0, 60, 135), 72: (80, 240, 150), 80: (150, 240, 255),
    81: (0, 0, 255), 99: (255, 255, 50), 252: (245, 150, 100), 253: (200, 40, 255),
    254: (30, 30, 255), 255: (90, 30, 150), 256: (255, 0, 0), 257: (250, 80, 100),
    258: (180, 30, 80), 259: (255, 0, 0),
}


def _rgb(sk_id: int) -> tuple[int, int, int]:
    b, g, r = SEMANTICKITTI_COLORS_BGR[sk_id]
    return (r, g, b)


# (name, SemanticKITTI id, thing, KITTI type, reflectivity range). Truck covers vans and
# trucks; the scene writes vans as KITTI "Van" (see scene.Things.kitti_type).
_TABLE = (
    ("unlabeled", 0, False, None, (0.1, 0.5)),
    ("road", 40, False, None, (0.08, 0.2)),          # asphalt
    ("sidewalk", 48, False, None, (0.25, 0.4)),      # concrete / paving
    ("terrain", 72, False, None, (0.3, 0.5)),        # grass, soil
    ("building", 50, False, None, (0.25, 0.55)),
    ("fence", 51, False, None, (0.2, 0.5)),
    ("vegetation", 70, False, None, (0.35, 0.55)),   # leaves are bright in the NIR
    ("trunk", 71, False, None, (0.2, 0.35)),
    ("pole", 80, False, None, (0.3, 0.55)),          # painted / galvanised metal
    ("traffic-sign", 81, False, None, (0.85, 0.97)),  # retroreflective sheeting
    ("car", 10, True, "Car", (0.1, 0.8)),           # paint varies a lot
    ("truck", 18, True, "Truck", (0.2, 0.7)),
    ("pedestrian", 30, True, "Pedestrian", (0.15, 0.45)),
    ("cyclist", 31, True, "Cyclist", (0.15, 0.5)),
)

CLASSES: tuple[ClassInfo, ...] = tuple(
    ClassInfo(i, n, sk, _rgb(sk), thing, kt, refl)
    for i, (n, sk, thing, kt, refl) in enumerate(_TABLE))
NUM_CLASSES = len(CLASSES)
CLASS_NAMES: tuple[str, ...] = tuple(c.name for c in CLASSES)
_BY_NAME = {c.name: c.id for c in CLASSES}

(UNLABELED, ROAD, SIDEWALK, TERRAIN, BUILDING, FENCE, VEGETATION, TRUNK, POLE,
 TRAFFIC_SIGN, CAR, TRUCK, PEDESTRIAN, CYCLIST) = range(NUM_CLASSES)
assert CLASS_NAMES[CYCLIST] == "cyclist" and CLASS_NAMES[TRAFFIC_SIGN] == "traffic-sign"

THING_CLASS_IDS: np.ndarray = np.array([c.id for c in CLASSES if c.is_thing], np.int32)
STUFF_CLASS_IDS: np.ndarray = np.array([c.id for c in CLASSES if not c.is_thing], np.int32)

# Materials that are not a whole class (parts of objects, ground paint): (lo, hi).
MATERIAL_REFLECTIVITY: dict[str, tuple[float, float]] = {
    "lane_paint": (0.55, 0.75),
    "glass": (0.05, 0.2),          # windows return little (specular / transmissive)
    "tyre": (0.03, 0.08),
    "license_plate": (0.85, 0.95),  # retroreflective
    "skin": (0.3, 0.45),
    "bike_frame": (0.2, 0.6),
}

# SemanticKITTI raw ids without a class of their own, mapped like semantic-kitti.yaml's
# learning_map does (moving-X -> X, lane-marking -> road, ...); everything else -> 0.
_EXTRA_FROM_SK = {
    13: TRUCK, 20: TRUCK, 258: TRUCK, 259: TRUCK, 257: TRUCK,  # bus / other-vehicle
    252: CAR, 253: CYCLIST, 254: PEDESTRIAN, 32: CYCLIST, 255: CYCLIST,
    60: ROAD, 44: ROAD, 49: TERRAIN, 52: BUILDING,
}

TO_SEMANTICKITTI: np.ndarray = np.array([c.semantickitti_id for c in CLASSES], np.int32)
FROM_SEMANTICKITTI: np.ndarray = np.zeros(max(SEMANTICKITTI_LABELS) + 1, np.int32)
for _sk, _ours in _EXTRA_FROM_SK.items():
    FROM_SEMANTICKITTI[_sk] = _ours
FROM_SEMANTICKITTI[TO_SEMANTICKITTI] = np.arange(NUM_CLASSES, dtype=np.int32)


def class_id(name: str) -> int:
    """Our id of a class name (KeyError if unknown)."""
    return _BY_NAME[name]


def class_name(cid: int) -> str:
    """Name of our class id."""
    return CLASSES[int(cid)].name


def is_thing(cid) -> np.ndarray | bool:
    """Whether class id(s) are thing classes (vectorized)."""
    a = np.asarray(cid)
    out = np.isin(a, THING_CLASS_IDS)
    return bool(out) if a.ndim == 0 else out


def kitti_type(cid: int) -> str | None:
    """KITTI object-label type of a thing class (None for stuff)."""
    return CLASSES[int(cid)].kitti_type


def to_semantickitti(ids) -> np.ndarray:
    """Our class ids -> SemanticKITTI raw label ids (uint32, semantic part only)."""
    return TO_SEMANTICKITTI[np.asarray(ids, dtype=np.int64)].astype(np.uint32)


def from_semantickitti(labels) -> np.ndarray:
    """SemanticKITTI labels -> our class ids (int32).

    Accepts full ``.label`` values (instance in the upper 16 bits, ignored); unknown raw
    ids map to unlabeled.
    """
    raw = np.asarray(labels).astype(np.int64) & 0xFFFF
    out = np.zeros(raw.shape, np.int32)
    ok = raw < len(FROM_SEMANTICKITTI)
    out[ok] = FROM_SEMANTICKITTI[raw[ok]]
    return out


def colors_rgb(normalized: bool = False) -> np.ndarray:
    """(NUM_CLASSES, 3) plot colours indexed by our id (uint8, or float in [0, 1])."""
    c = np.array([ci.rgb for ci in CLASSES], np.uint8)
    return c / 255.0 if normalized else c


def sample_reflectivity(rng: np.random.Generator, cid: int | None = None, n=None, *,
                        material: str | None = None):
    """Uniform reflectivity sample(s) for a class (or a named ``material``)."""
    lo, hi = MATERIAL_REFLECTIVITY[material] if material else CLASSES[int(cid)].reflectivity
    return rng.uniform(lo, hi, n)


def semantickitti_class_map(path: str | Path | None = None) -> dict:
    """A semantic-kitti.yaml style class map for our classes (optionally written as yaml).

    Keys: ``labels`` (raw id -> name, the full SemanticKITTI set), ``color_map`` (raw id
    -> [b, g, r], BGR as SemanticKITTI), ``learning_map`` (raw id -> our id),
    ``learning_map_inv`` (our id -> raw id), ``learning_ignore`` (our id -> bool,
    unlabeled ignored), ``class_names`` (our id -> our name), ``things`` (thing ids).
    """
    cmap = {
        "name": "lidar_sim",
        "labels": dict(SEMANTICKITTI_LABELS),
        "color_map": {k: list(v) for k, v in SEMANTICKITTI_COLORS_BGR.items()},
        "learning_map": {k: int(FROM_SEMANTICKITTI[k]) for k in SEMANTICKITTI_LABELS},
        "learning_map_inv": {c.id: c.semantickitti_id for c in CLASSES},
        "learning_ignore": {c.id: c.id == UNLABELED for c in CLASSES},
        "class_names": {c.id: c.name for c in CLASSES},
        "things": [int(i) for i in THING_CLASS_IDS],
    }
    if path is not None:
        import yaml  # only needed for writing
        with open(path, "w", encoding="utf-8") as f:
            yaml.safe_dump(cmap, f, sort_keys=False)
    return cmap
