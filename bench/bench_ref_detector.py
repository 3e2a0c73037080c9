"""Reference perception detector figures on one simulated HDL-64 frame (64 x 2048 beams,
~118k points), one thread (the models are loaded with ``n_jobs=1``):

``ref.detector_ms``: ``ReferenceDetector.detect`` (ground, clustering, box fits, features,
classifier, box refinement, NMS); ``ref.mimo_ms``: ``MultiHeadDetector.detect`` with the
trained heads (K = 2 by default: shared front end, per-head models and NMS).
Target for both: <= 200 ms (5 Hz on one core). Needs the trained models in
``models/reference`` (``python -m reference_perception.detector train``, ``... multihead
train``); without them no figure is produced.
"""
from __future__ import annotations

import sys

from lidar_sim.frames import sequence_frames
from reference_perception.detector import ReferenceDetector, default_model_dir
from reference_perception.multihead import MultiHeadDetector


def figures():
    d = default_model_dir()
    if not (d / "detector.json").is_file() or not (d / "multihead.json").is_file():
        print(f"bench_ref_detector: no trained models in {d}, skipped", file=sys.stderr)
        return
    f = next(sequence_frames(seed=7000, n_frames=1))
    det = ReferenceDetector(d)
    mimo = MultiHeadDetector(d)
    yield "ref.detector_ms", lambda: det.detect(f.xyz, f.intensity, f.ring)
    yield "ref.mimo_ms", lambda: mimo.detect(f.xyz, f.intensity, f.ring)
