"""Whole simulated frame: ``sim.frame_ms`` = one ``simulate_frame`` of a generated street
(HDL-64, 64 x 2048 beams, ~80 objects in range), i.e. the scan plus the per-object ground
truth (points per object, occlusion by re-casting each object alone, truncation).
Target <= 200 ms (5 frames/s on one core).

Each repetition simulates the next of ``N_FRAMES`` consecutive frames of the demo split's
first sequence (primitives prepared beforehand), so the median covers a moving scene, not
one frame's luck. ``python bench/bench_sim_frame.py`` also prints ``sim.points_per_frame``
(a count, not a time: bench/run.py records milliseconds only).
"""
from __future__ import annotations

import itertools
import sys
import time

import numpy as np

from lidar_sim.sensor import hdl64
from lidar_sim.sequence import generate_sequence
from lidar_sim.simulate import simulate_frame

SEED = 7000       # split "demo", sequence 0
SEQ_FRAMES = 100  # the demo split's length: the drive is planned over it
N_FRAMES = 10


def _setup():
    cfg = hdl64()
    seq = generate_sequence(SEED, SEQ_FRAMES)
    fps = [seq.frame(i, max_range=cfg.max_range) for i in range(N_FRAMES)]
    return cfg, fps, np.random.default_rng(SEED)


def figures():
    cfg, fps, rng = _setup()
    frames = itertools.cycle(fps)
    yield "sim.frame_ms", lambda: simulate_frame(next(frames), cfg, rng)


def main() -> int:
    cfg, fps, rng = _setup()
    for fp in fps[:2]:  # warm-up: direction cache, first-call allocations
        simulate_frame(fp, cfg, rng)
    ms, points, objects = [], [], []
    for fp in fps:
        t0 = time.perf_counter()
        f = simulate_frame(fp, cfg, rng)
        ms.append((time.perf_counter() - t0) * 1e3)
        points.append(len(f.xyz))
        objects.append(len(f.gt_boxes))
    print(f"sim.frame_ms          median {np.median(ms):8.1f}  (min {min(ms):.1f}, "
          f"max {max(ms):.1f}; {len(ms)} frames, {np.mean(objects):.0f} objects)")
    print(f"sim.points_per_frame  mean   {np.mean(points):8.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
