"""Annotation-error injection: an "as annotated" ground truth with known mistakes.

Box errors (per object, independently): missing (unlabelled), shifted (centre moved in
BEV), resized (l, w, h scaled), wrong class (a confusable class). Segmentation errors:
mislabelled regions (all points within a radius of a seed point relabelled to one
class). Every applied error is returned as a record; ``apply_records`` replays records
on clean ground truth, so the list is checkably exactly what was done.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class AnnotationErrorConfig:
    p_missing: float = 0.05       # share of objects left unlabelled
    p_shift: float = 0.05         # share of boxes whose centre moves
    shift_std: float = 0.4        # [m] per BEV axis
    p_resize: float = 0.05        # share of boxes scaled
    resize_std: float = 0.15      # relative, per dimension
    p_wrong_class: float = 0.03   # share of boxes given a confusable class
    regions_per_frame: float = 0.5  # mean number (Poisson) of mislabelled point regions
    region_radius: tuple[float, float] = (0.5, 2.0)  # [m], uniform


def inject_box_errors(boxes: np.ndarray, classes: np.ndarray, instances: np.ndarray,
                      confusions: dict[int, list[int]], rng: np.random.Generator,
                      cfg: AnnotationErrorConfig = AnnotationErrorConfig()) -> list[dict]:
    """Draw box errors for one frame; returns records (apply them with ``apply_records``).

    An object is either missing or gets any of shift / resize / wrong class. Records hold
    the instance id, the kind and the new values.
    """
    records = []
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    for i in range(len(boxes)):  # bounded: objects of one frame
        inst = int(instances[i])
        if rng.random() < cfg.p_missing:
            records.append({"kind": "missing", "instance": inst})
            continue
        if rng.random() < cfg.p_shift:
            dx, dy = rng.normal(0.0, cfg.shift_std, 2)
            records.append({"kind": "shifted", "instance": inst, "dx": float(dx), "dy": float(dy)})
        if rng.random() < cfg.p_resize:
            s = np.clip(1.0 + rng.normal(0.0, cfg.resize_std, 3), 0.5, 1.5)
            records.append({"kind": "resized", "instance": inst, "scale_lwh": [float(v) for v in s]})
        options = confusions.get(int(classes[i]), [])
        if options and rng.random() < cfg.p_wrong_class:
            records.append({"kind": "wrong_class", "instance": inst,
                            "from_class": int(classes[i]), "to_class": int(rng.choice(options))})
    return records


def inject_region_errors(xyz: np.ndarray, labels: np.ndarray, region_classes: list[int],
                         rng: np.random.Generator,
                         cfg: AnnotationErrorConfig = AnnotationErrorConfig()) -> list[dict]:
    """Draw mislabelled point regions: a seed point, a radius and a new class differing
    from the seed's label; records list the centre, radius, class and point count."""
    records = []
    n = len(xyz)
    if n == 0 or not region_classes:
        return records
    for _ in range(rng.poisson(cfg.regions_per_frame)):
        seed = int(rng.integers(n))
        choices = [c for c in region_classes if c != int(labels[seed])]
        if not choices:
            continue
        radius = float(rng.uniform(*cfg.region_radius))
        centre = np.asarray(xyz[seed], dtype=np.float64)
        inside = np.linalg.norm(np.asarray(xyz, dtype=np.float64) - centre, axis=1) <= radius
        records.append({"kind": "mislabeled_region", "centre": [float(v) for v in centre],
                        "radius": radius, "to_class": int(rng.choice(choices)),
                        "points": int(inside.sum())})
    return records


def apply_records(records: list[dict], boxes, classes, instances, xyz=None, labels=None):
    """Apply ``records`` to clean ground truth; returns the annotated (boxes, classes,
    instances, labels) — arrays are copies, missing objects removed."""
    boxes = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    classes = np.array(classes).copy()
    instances = np.array(instances).copy()
    labels = None if labels is None else np.array(labels).copy()
    row = {int(k): i for i, k in enumerate(instances)}
    drop = []
    for r in records:
        kind = r["kind"]
        if kind == "mislabeled_region":
            inside = np.linalg.norm(np.asarray(xyz, np.float64) - r["centre"], axis=1) <= r["radius"]
            labels[inside] = r["to_class"]
            continue
        i = row[r["instance"]]
        if kind == "missing":
            drop.append(i)
        elif kind == "shifted":
            boxes[i, 0] += r["dx"]
            boxes[i, 1] += r["dy"]
        elif kind == "resized":
            boxes[i, 3:6] *= r["scale_lwh"]
        elif kind == "wrong_class":
            classes[i] = r["to_class"]
        else:
            raise ValueError(f"unknown annotation error kind {kind!r}")
    keep = np.setdiff1d(np.arange(len(boxes)), drop)
    return boxes[keep], classes[keep], instances[keep], labels


def config_dict(cfg: AnnotationErrorConfig) -> dict:
    """The configuration as written beside the error list."""
    return asdict(cfg)
