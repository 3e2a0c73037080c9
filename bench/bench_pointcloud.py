"""PointCloud2 decode / build figures (see bench/run.py for the contract)."""
from __future__ import annotations

import numpy as np

N_POINTS = 120_000


def _columns(n: int = N_POINTS) -> dict[str, np.ndarray]:
    """x, y, z, intensity float32 columns of a 16-ring spinning-lidar-like scan."""
    rng = np.random.default_rng(0)
    ring = np.arange(n) % 16
    azimuth = np.linspace(0.0, 2 * np.pi, n // 16 + 1).repeat(16)[:n]
    elevation = np.deg2rad(-15.0 + 2.0 * ring)
    rng_m = rng.uniform(1.0, 60.0, n)
    rng_m[rng.random(n) < 0.05] = np.nan  # missing returns, as real drivers emit them
    cols = {
        "x": rng_m * np.cos(elevation) * np.cos(azimuth),
        "y": rng_m * np.cos(elevation) * np.sin(azimuth),
        "z": rng_m * np.sin(elevation),
        "intensity": rng.uniform(0.0, 255.0, n),
    }
    return {k: v.astype(np.float32) for k, v in cols.items()}


def figures():
    from lidar_quality_core.pointcloud import create_cloud, xyz_intensity

    cols = _columns()
    msg = create_cloud(None, cols)
    assert msg.point_step == 16 and len(msg.data) == 16 * N_POINTS

    yield "core.cloud_decode_120k_ms", lambda: xyz_intensity(msg)
    yield "core.cloud_build_120k_ms", lambda: create_cloud(None, cols)
    yield "baseline.copy_cloud_120k_ms", lambda: np.frombuffer(msg.data, np.uint8).copy()
