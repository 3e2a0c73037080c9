"""Publication thresholds on the meta confidence: a floor, one per class, one per range bin.

What Autoware users ask of a detector's score (per-class and per-distance thresholds),
applied to the meta confidence: a detection is published when its confidence is at least
the largest of ``floor`` (``min_confidence``), its class's threshold and its range bin's.
Range: bird's-eye distance of the box centre from the sensor (the origin of the cloud's
frame; for MIMO, of the first head's). A NaN confidence passes only when every threshold
that applies is 0. Removed detections are counted by class and range bin
(``removed.<class>.<bin>``, e.g. ``removed.car.30-60m``); the quality outputs still list
them all.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from .parameters import param

__all__ = ["ConfidenceThresholds", "parse_class_thresholds", "parse_range_thresholds",
           "from_parameters", "class_thresholds_param", "range_thresholds_param"]


def parse_class_thresholds(text: str) -> dict[str, float]:
    """``"car:0.3 pedestrian:0.2"`` (spaces or commas) -> ``{"car": 0.3, ...}``."""
    out = {}
    for item in text.replace(",", " ").split():
        name, sep, value = item.rpartition(":")
        try:
            v = float(value)
        except ValueError:
            v = None
        if not sep or not name or v is None or not 0.0 <= v <= 1.0:
            raise ValueError(f"class threshold {item!r}: expected class_name:value with a "
                             "value in [0, 1]")
        out[name] = v
    return out


def parse_range_thresholds(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``"30:0.1 60:0.3"`` (from 30 m on 0.1, from 60 m on 0.3) -> ``(edges (30, 60),
    per-bin thresholds (0, 0.1, 0.3))``; empty text: no bins."""
    pairs = []
    for item in text.replace(",", " ").split():
        start, sep, value = item.partition(":")
        try:
            pairs.append((float(start), float(value)))
        except ValueError:
            raise ValueError(f"range threshold {item!r}: expected from_metres:value") from None
        if not sep:
            raise ValueError(f"range threshold {item!r}: expected from_metres:value")
    pairs.sort()
    return tuple(a for a, _ in pairs), ((0.0, *(b for _, b in pairs)) if pairs else ())


@dataclass
class ConfidenceThresholds:
    floor: float = 0.0
    per_class: dict[str, float] = field(default_factory=dict)
    range_edges: tuple[float, ...] = ()   # ascending bin edges [m]
    per_range: tuple[float, ...] = ()     # one per bin: len(range_edges) + 1 (or none)

    def __post_init__(self):
        self.range_edges = tuple(float(x) for x in self.range_edges)
        self.per_range = tuple(float(x) for x in self.per_range)
        if self.per_range and len(self.per_range) != len(self.range_edges) + 1:
            raise ValueError(f"{len(self.per_range)} range thresholds for "
                             f"{len(self.range_edges)} range bin edges: give one more threshold "
                             "than edges (bins below the first edge, between edges, above the "
                             "last)")
        if not self.per_range and self.range_edges:
            raise ValueError("range bin edges without range thresholds")
        if any(b <= a for a, b in zip(self.range_edges, self.range_edges[1:])) or any(
                e <= 0 for e in self.range_edges):
            raise ValueError(f"range bin edges must be positive and ascending, got "
                             f"{list(self.range_edges)}")
        bad = [v for v in (self.floor, *self.per_class.values(), *self.per_range)
               if not 0.0 <= v <= 1.0]
        if bad:
            raise ValueError(f"thresholds must lie in [0, 1], got {bad}")

    @property
    def active(self) -> bool:
        return bool(self.floor > 0 or any(self.per_class.values()) or any(self.per_range))

    def bin_names(self) -> list[str]:
        """``["0-30m", "30-60m", ">=60m"]`` for edges (30, 60); ``["all"]`` without bins."""
        e = [f"{x:g}" for x in self.range_edges]
        if not e:
            return ["all"]
        return [f"0-{e[0]}m", *(f"{a}-{b}m" for a, b in zip(e, e[1:])), f">={e[-1]}m"]

    def bins(self, boxes) -> np.ndarray:
        """Range bin of each box (N, >= 2: x, y first)."""
        b = np.asarray(boxes, np.float64).reshape(len(boxes), -1)
        return np.searchsorted(np.asarray(self.range_edges), np.hypot(b[:, 0], b[:, 1]),
                               side="right")

    def keep(self, confidence, labels, boxes) -> tuple[np.ndarray, Counter]:
        """``(kept (N,) bool, removed counts by "removed.<class>.<bin>")``."""
        conf = np.asarray(confidence, np.float64).reshape(-1)
        if not self.active:
            return np.ones(len(conf), bool), Counter()
        bins = self.bins(boxes)
        thr = np.full(len(conf), self.floor)
        if self.per_class:
            thr = np.maximum(thr, [self.per_class.get(c, 0.0) for c in labels])
        if self.per_range:
            thr = np.maximum(thr, np.asarray(self.per_range)[bins])
        with np.errstate(invalid="ignore"):
            kept = (conf >= thr) | ((thr <= 0) & np.isnan(conf))
        names = self.bin_names()
        removed = Counter(f"removed.{labels[i] or 'unknown'}.{names[bins[i]]}"
                          for i in np.flatnonzero(~kept).tolist())
        return kept, removed


def from_parameters(min_confidence: float, class_text: str, range_text: str
                    ) -> ConfidenceThresholds:
    """The thresholds of the nodes' parameters (``ValueError`` naming a bad entry)."""
    edges, per_range = parse_range_thresholds(range_text)
    return ConfidenceThresholds(min_confidence, parse_class_thresholds(class_text), edges,
                                per_range)


def class_thresholds_param(output: str):
    """The ``class_min_confidence`` parameter field."""
    return param("", f"Per-class thresholds on the meta confidence for {output}: "
                 "'class:value' entries, e.g. 'car:0.3 pedestrian:0.2' (a class not listed: "
                 "min_confidence only). Removed detections are counted by class and range bin "
                 "(removed.<class>.<bin>); the quality output lists them all.")


def range_thresholds_param(output: str):
    """The ``range_min_confidence`` parameter field."""
    return param("", f"Per-range thresholds on the meta confidence for {output}: "
                 "'from_metres:value' entries, e.g. '30:0.1 60:0.3' (0.1 from 30 m, 0.3 from "
                 "60 m, none closer); range = bird's-eye distance of the box centre from the "
                 "sensor. A detection needs the largest of min_confidence, its class's and its "
                 "range's threshold.")
