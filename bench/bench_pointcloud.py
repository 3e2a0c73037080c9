"""PointCloud2 decode / build figures (see bench/run.py for the contract), and the two
baselines: one copy of a 120k-point cloud (the floor of any per-point step) and
``baseline.python_loop_ms``, a fixed pure-Python workload (``sum(range(10**6))``) that says
how fast this host runs the interpreter at bench time. The shared 2-core machines of this
class differ by 2x and more from one day to the next (on 2026-12-02 ``lms.metrics_ms``,
code unchanged, took 28 ms against 9.3-13.5 on the days before, and this loop 19-29 ms),
and the nodes' frame costs follow them: read a bench's figures beside its baselines."""
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
    yield "baseline.python_loop_ms", lambda: sum(range(1_000_000))
