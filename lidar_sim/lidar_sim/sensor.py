"""Rotating multi-beam lidar model on top of :func:`lidar_sim.raycast.cast`.

Conventions (ROS: x forward, y left, z up; azimuth counter-clockwise from +x):

- ring 0 is the TOP beam; ``elevations_deg`` is strictly decreasing with the ring index,
  so ring = row of a range image (as Ouster / SemanticKITTI range images; note the ROS
  velodyne driver numbers rings from the bottom instead).
- column j fires at azimuth ``azimuth_offset + pi * (1 - (2 j + 1) / columns)``, wrapped
  to [-pi, pi): column 0 looks just left of straight back, columns advance clockwise
  seen from above (like a Velodyne), the middle columns look forward. This is the
  SemanticKITTI projection ``u = floor((1 - atan2(y, x) / pi) / 2 * columns)``.
- points come out column-major (firing order): by column, then ring 0 (top) down.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .primitives import Primitives
from .raycast import cast


@dataclass
class SensorConfig:
    """Beam layout and noise model of a spinning lidar.

    Dropout probability of a return at range r on a surface of reflectivity rho:
    ``dropout_base + dropout_range * (r / max_range)**2 + dropout_dark * (1 - rho)**2``.
    Intensity: ``rho * cos(incidence) * exp(-r / intensity_falloff_m)`` plus Gaussian
    noise, clipped to [0, 1]. ``mount_height`` is informational: the scene puts the
    ground at ``Primitives.ground_z = -mount_height``; ``scan`` only reads the primitives.
    """

    elevations_deg: np.ndarray
    columns: int = 2048
    max_range: float = 120.0
    min_range: float = 0.9
    mount_height: float = 1.73
    range_noise_std: float = 0.02
    dropout_base: float = 0.005
    dropout_range: float = 0.15
    dropout_dark: float = 0.15
    intensity_noise_std: float = 0.02
    intensity_falloff_m: float = 300.0
    azimuth_offset_deg: float = 0.0
    name: str = field(default="custom")

    def __post_init__(self):
        e = np.asarray(self.elevations_deg, dtype=np.float64).ravel()
        if e.size == 0 or np.any(np.diff(e) >= 0):
            raise ValueError("elevations_deg must be non-empty and strictly decreasing "
                             "(ring 0 = top beam)")
        self.elevations_deg = e
        self.columns = int(self.columns)
        if self.columns < 1:
            raise ValueError("columns must be >= 1")

    @property
    def channels(self) -> int:
        return len(self.elevations_deg)


def hdl64(**kw) -> SensorConfig:
    """Velodyne HDL-64E-like: +2.0 to -24.8 deg; upper block of 32 beams down to -8.33
    at ~1/3 deg, lower block of 32 from -8.83 at ~1/2 deg."""
    e = np.r_[np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)]
    return SensorConfig(e, name="hdl64", **kw)


def hdl32(**kw) -> SensorConfig:
    """Velodyne HDL-32E-like: 32 beams uniform from +10.67 to -30.67 deg (1.33 deg)."""
    return SensorConfig(np.linspace(10.67, -30.67, 32), name="hdl32", **kw)


def vls128(**kw) -> SensorConfig:
    """128-beam (VLS-128-like): +15 to -25 deg, 0.125 deg spacing from +3 to -6.875,
    ~0.85 deg above and ~0.55 deg below that band."""
    e = np.r_[np.linspace(15.0, 3.125, 15), np.linspace(3.0, -6.875, 80),
              np.linspace(-7.4, -25.0, 33)]
    return SensorConfig(e, name="vls128", **kw)


def column_azimuths(cfg: SensorConfig) -> np.ndarray:
    """(columns,) firing azimuth in radians, in [-pi, pi)."""
    j = np.arange(cfg.columns)
    a = np.deg2rad(cfg.azimuth_offset_deg) + np.pi * (1.0 - (2.0 * j + 1.0) / cfg.columns)
    return np.mod(a + np.pi, 2 * np.pi) - np.pi


def beam_directions(cfg: SensorConfig) -> np.ndarray:
    """(channels, columns, 3) unit beam vectors, indexed [ring, column]."""
    e = np.deg2rad(cfg.elevations_deg)[:, None]
    a = column_azimuths(cfg)[None, :]
    ce = np.cos(e)
    return np.stack(np.broadcast_arrays(ce * np.cos(a), ce * np.sin(a), np.sin(e)), axis=-1)


_DIR_CACHE: dict = {}


def _dirs_cached(cfg: SensorConfig) -> np.ndarray:
    key = (cfg.elevations_deg.tobytes(), cfg.columns, float(cfg.azimuth_offset_deg))
    d = _DIR_CACHE.get(key)
    if d is None:
        if len(_DIR_CACHE) > 8:
            _DIR_CACHE.clear()
        d = np.ascontiguousarray(beam_directions(cfg).reshape(-1, 3))
        d.flags.writeable = False
        _DIR_CACHE[key] = d
    return d


@dataclass
class Scan:
    """One revolution; per-point arrays in column-major (firing) order.

    ``xyz`` float32 sensor frame (relative to the sensor origin), ``range`` float32
    metres (noisy), ``intensity`` float32 in [0, 1], ``ring`` / ``column`` uint16,
    ``semantic`` / ``instance`` int32 ground truth of the surface hit.
    """

    xyz: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    column: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    range: np.ndarray

    def __len__(self) -> int:
        return len(self.range)


def scan(prims: Primitives, cfg: SensorConfig, rng=None, *, origin=(0.0, 0.0, 0.0)) -> Scan:
    """Simulate one revolution of ``cfg`` at ``origin`` (primitives' frame, axes shared).

    ``rng``: Generator or seed (None: fresh entropy). Rays without a hit within
    max_range, returns closer than min_range (after noise) and dropouts give no point.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    C, W = cfg.channels, cfg.columns
    d = _dirs_cached(cfg)  # ring-major: nearly the caster's internal order
    h = cast(prims, origin, d, cfg.max_range, rng)

    # column-major selection of the rays that returned something
    hit = (h.kind > 0).reshape(C, W)
    col, ring = np.nonzero(hit.T)
    flat = ring * W + col
    t = h.t[flat]
    m = len(flat)
    refl = h.reflectivity[flat]

    r = t + cfg.range_noise_std * rng.standard_normal(m) if cfg.range_noise_std > 0 else t
    p_drop = (cfg.dropout_base + cfg.dropout_range * (t / cfg.max_range) ** 2
              + cfg.dropout_dark * (1.0 - np.clip(refl, 0.0, 1.0)) ** 2)
    keep = (r >= cfg.min_range) & (r <= cfg.max_range) & (rng.random(m) >= p_drop)
    flat, r, refl = flat[keep], r[keep], refl[keep]
    dd = np.take(d, flat, axis=0)  # np.take: far faster than fancy row indexing

    cos_inc = np.abs(np.einsum("ij,ij->i", np.take(h.normal, flat, axis=0), dd))
    inten = refl * cos_inc
    if np.isfinite(cfg.intensity_falloff_m) and cfg.intensity_falloff_m > 0:
        inten = inten * np.exp(-r / cfg.intensity_falloff_m)
    if cfg.intensity_noise_std > 0:
        inten = inten + cfg.intensity_noise_std * rng.standard_normal(len(r))
    return Scan(
        xyz=(dd * r[:, None]).astype(np.float32),
        intensity=np.clip(inten, 0.0, 1.0).astype(np.float32),
        ring=ring[keep].astype(np.uint16),
        column=col[keep].astype(np.uint16),
        semantic=h.semantic[flat],
        instance=h.instance[flat],
        range=r.astype(np.float32),
    )
