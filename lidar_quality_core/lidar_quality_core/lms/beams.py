"""Which image row a lidar beam takes: ring-field names, per-beam elevation tables and
sensor presets (numpy only; the range image itself is :mod:`.projection`).

Drivers name the beam index differently (``ring``: velodyne_driver, Ouster, Autoware's
PointXYZIRC; ``channel``: nebula; ``laser_id`` / ``laser_number``: others) and number it
differently (ring 0 = lowest beam, ring 0 = top beam, or laser order, interleaved in
elevation on older Velodynes). The one quantity that does not depend on the driver is the
elevation of a beam's points: :func:`beam_elevations` takes the median elevation of each
beam index, :class:`BeamTable` keeps it across frames, and :func:`rows_of_beams` places each
beam in the row whose elevation bin holds it (a sensor's elevation table) or by its rank
(no table: the highest beam is row 0).

Presets (:func:`load_presets`): a YAML mapping ``name -> {channels, elevations_deg |
fov_up_deg / fov_down_deg, azimuth_resolution_deg, description}``; the image width is
``round(360 / azimuth_resolution_deg)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .projection import RangeImageConfig

__all__ = ["RING_FIELD_NAMES", "ring_field_names", "find_ring_field", "elevation_deg",
           "beam_elevations", "BeamTable", "rows_of_beams", "elevation_rows", "SensorPreset", "load_presets",
           "parse_degrees"]

#: Beam-index field names tried by ``ring_field: auto``, in this order.
RING_FIELD_NAMES = ("ring", "channel", "laser_id", "laser_number", "laser", "beam",
                    "beam_id", "line", "scan_line")
#: A beam needs this many points in a frame before its median elevation is trusted.
MIN_BEAM_POINTS = 3


def ring_field_names(spec: str) -> tuple[str, ...]:
    """Candidate ring field names of a ``ring_field`` setting: ``auto`` for
    :data:`RING_FIELD_NAMES`, else a comma-separated list (``"ring"``, ``"ring, channel"``);
    ``ValueError`` when it names no field."""
    spec = (spec or "").strip()
    if spec.lower() == "auto":
        return RING_FIELD_NAMES
    names = tuple(s.strip() for s in spec.split(",") if s.strip())
    if not names:
        raise ValueError(f"ring_field {spec!r} names no field (auto tries "
                         f"{', '.join(RING_FIELD_NAMES)})")
    return names


def find_ring_field(field_names: Iterable[str], spec: str) -> str | None:
    """The first candidate of ``spec`` that the cloud has, or None."""
    have = set(field_names)
    return next((nm for nm in ring_field_names(spec) if nm in have), None)


def elevation_deg(xyz) -> np.ndarray:
    """(N,) float64 elevation ``asin(z / r)`` in degrees; NaN where r is 0 or not finite."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt((xyz * xyz).sum(axis=1))
        el = np.degrees(np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0)))
    el[~(r > 0)] = np.nan
    return el


def beam_elevations(beam, el, n_beams: int, min_points: int = MIN_BEAM_POINTS) -> np.ndarray:
    """(n_beams,) median elevation [deg] of the points of each beam index ``0..n_beams-1``
    (``beam`` (N,) ints, ``el`` (N,) degrees, NaN for points to ignore); NaN for a beam
    with fewer than ``min_points`` points."""
    beam = np.asarray(beam).reshape(-1)
    el = np.asarray(el, dtype=np.float64).reshape(-1)
    ok = np.isfinite(el) & (beam >= 0) & (beam < n_beams)
    b, e = beam[ok].astype(np.int64), el[ok]
    out = np.full(n_beams, np.nan)
    if not len(b):
        return out
    order = np.lexsort((e, b))
    b, e = b[order], e[order]
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    counts = np.diff(np.r_[starts, len(b)])
    for s, c in zip(starts.tolist(), counts.tolist()):
        if c >= min_points:
            out[b[s]] = 0.5 * (e[s + (c - 1) // 2] + e[s + c // 2])
    return out


class BeamTable:
    """Per-beam elevations estimated from the clouds, kept across frames (one per node):
    a beam's first estimate stays, beams seen later are added. Rows (:func:`rows_of_beams`)
    are recomputed only when a beam is added."""

    def __init__(self, n_beams: int):
        self.elevations = np.full(int(n_beams), np.nan)
        self.version = 0
        self._rows_key = None
        self._rows = None

    def update(self, beam, el) -> bool:
        """Add the beams of this frame not known yet; True when the table changed."""
        est = beam_elevations(beam, el, len(self.elevations))
        new = np.isnan(self.elevations) & np.isfinite(est)
        if new.any():
            self.elevations[new] = est[new]
            self.version += 1
            return True
        return False

    @property
    def n_known(self) -> int:
        return int(np.isfinite(self.elevations).sum())

    def rows(self, cfg: RangeImageConfig | None, rows: int) -> np.ndarray:
        """:func:`rows_of_beams` of the table (a copy, recomputed when the table changed)."""
        key = (self.version, cfg, rows)
        if key != self._rows_key:
            self._rows, self._rows_key = rows_of_beams(self.elevations, cfg, rows), key
        return self._rows.copy()


def rows_of_beams(beam_el, cfg: RangeImageConfig | None, rows: int) -> np.ndarray:
    """(B,) int32 image row of each beam index from its elevation ``beam_el`` (NaN:
    unknown, row -1). With ``cfg`` holding an elevation table (or a uniform field of view)
    the row whose elevation bin holds the beam (-1 outside the image); ``cfg`` None: the
    beam's rank by elevation, highest = row 0 (-1 beyond ``rows``)."""
    e = np.asarray(beam_el, dtype=np.float64).reshape(-1)
    out = np.full(len(e), -1, np.int32)
    known = np.isfinite(e)
    if cfg is None:
        idx = np.flatnonzero(known)
        order = idx[np.argsort(-e[idx], kind="stable")]
        rank = np.arange(len(order))
        keep = rank < rows
        out[order[keep]] = rank[keep]
        return out
    return elevation_rows(e, cfg)


def elevation_rows(el, cfg: RangeImageConfig) -> np.ndarray:
    """(N,) int32 row whose elevation bin holds each elevation ``el`` [deg] (-1 outside the
    image or NaN), as :func:`.projection.project` bins points without a ring."""
    e = np.asarray(el, dtype=np.float64).reshape(-1)
    out = np.full(len(e), -1, np.int32)
    ok = np.isfinite(e)
    r = np.searchsorted(-cfg.row_edges_deg, -e[ok], side="right") - 1
    r[(r < 0) | (r >= cfg.rows)] = -1
    out[ok] = r
    return out


def parse_degrees(text) -> tuple[float, ...]:
    """A comma / space separated list of degrees (or a sequence of numbers) as a tuple;
    ``ValueError`` naming the bad entry."""
    if isinstance(text, str):
        # "[15, 13]" too: a YAML list given where the parameter is a string
        parts = [p for p in text.strip().strip("[]").replace(",", " ").split() if p]
    else:
        parts = list(text or ())
    out = []
    for p in parts:
        try:
            v = float(p)
        except (TypeError, ValueError):
            raise ValueError(f"not a number of degrees: {p!r}") from None
        if not np.isfinite(v) or not -90.0 <= v <= 90.0:
            raise ValueError(f"beam elevation {v} is outside [-90, 90] deg")
        out.append(v)
    return tuple(out)


@dataclass(frozen=True)
class SensorPreset:
    """A sensor's range image: one row per beam (``elevations_deg``, top first) and
    ``width`` = 360 deg / the azimuth resolution at 10 Hz."""

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_resolution_deg: float
    description: str = ""

    @property
    def channels(self) -> int:
        return len(self.elevations_deg)

    @property
    def width(self) -> int:
        return int(round(360.0 / self.azimuth_resolution_deg))

    def range_config(self) -> RangeImageConfig:
        return RangeImageConfig.from_elevations(self.elevations_deg, self.width)


def _preset(name: str, d: dict) -> SensorPreset:
    if not isinstance(d, dict):
        raise ValueError(f"sensor preset {name!r} must be a mapping")
    unknown = set(d) - {"channels", "elevations_deg", "fov_up_deg", "fov_down_deg",
                        "azimuth_resolution_deg", "description"}
    if unknown:
        raise ValueError(f"sensor preset {name!r}: unknown keys {sorted(unknown)}")
    n = d.get("channels")
    if "elevations_deg" in d:
        el = parse_degrees(d["elevations_deg"])
        if n is not None and int(n) != len(el):
            raise ValueError(f"sensor preset {name!r}: channels {n} but {len(el)} elevations")
    elif "fov_up_deg" in d and "fov_down_deg" in d and n:
        # uniform beams: the first and last beam are at the edges
        el = tuple(float(v) for v in np.linspace(float(d["fov_up_deg"]),
                                                 float(d["fov_down_deg"]), int(n)))
    else:
        raise ValueError(f"sensor preset {name!r} needs elevations_deg, or channels with "
                         "fov_up_deg and fov_down_deg")
    el = tuple(sorted(el, reverse=True))
    if len(set(el)) != len(el):
        raise ValueError(f"sensor preset {name!r}: two beams at the same elevation")
    az = float(d.get("azimuth_resolution_deg", 0))
    if not 0.005 <= az <= 10:
        raise ValueError(f"sensor preset {name!r}: azimuth_resolution_deg must be in "
                         f"[0.005, 10], got {az}")
    return SensorPreset(name, el, az, str(d.get("description", "")))


def load_presets(path: str | Path) -> dict[str, SensorPreset]:
    """The presets of a YAML file (see the module doc); ``ValueError`` naming the bad one."""
    import yaml

    data = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of sensor name -> preset")
    return {str(k): _preset(str(k), v) for k, v in data.items()}


def preset_names(presets: Sequence[SensorPreset] | dict) -> str:
    return ", ".join(sorted(presets))
