"""Reference segmenter figure: ``ref.segmenter_ms`` = ``ReferenceSegmenter.predict_proba``
(features incl. ground estimate and range image, then the MLP) on one simulated HDL-64
frame (64 x 2048, ~118k points) on ONE thread (target <= 200 ms, i.e. >= 5 Hz; aim 100).

Uses the shipped model ``models/reference/segmenter.joblib``; without it the figure is
skipped with a message (train it with ``python -m reference_perception.segmenter train``).
"""
from __future__ import annotations

import sys


def figures():
    from reference_perception.segmenter import DEFAULT_MODEL_PATH, ReferenceSegmenter

    if not DEFAULT_MODEL_PATH.exists():
        print(f"ref.segmenter_ms: skipped, no model at {DEFAULT_MODEL_PATH} (train it with "
              "`python -m reference_perception.segmenter train`)", file=sys.stderr)
        return
    from threadpoolctl import threadpool_limits

    from lidar_sim.frames import split_frames

    seg = ReferenceSegmenter.load()
    f = next(split_frames("reference_test", sequences=[0]))
    # one BLAS thread only while this figure is timed (run.py times it before resuming us)
    with threadpool_limits(limits=1):
        yield "ref.segmenter_ms", lambda: seg.predict_proba(f.xyz, f.intensity, f.ring)


if __name__ == "__main__":
    import time

    import numpy as np

    for name, fn in figures():
        t = []
        for _ in range(20):
            t0 = time.perf_counter()
            fn()
            t.append((time.perf_counter() - t0) * 1e3)
        print(f"{name}: median {np.median(t):.1f} ms")
