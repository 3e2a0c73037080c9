"""``make reference-models``: retrain the whole reference perception and report its
held-out quality.

    python -m reference_perception.train --out models/reference [--only detector segmenter multihead]

Trains on the ``reference_train`` split and evaluates on ``reference_test`` (simulated
sequences disjoint from the meta models' splits, see ``lidar_sim.splits``), then writes
``quality.json`` beside the models with every figure printed.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from lidar_quality_core.jsonable import jsonable

PARTS = ("segmenter", "detector", "multihead")


def main(argv=None) -> int:
    from lidar_quality_core.model_store import models_dir

    ap = argparse.ArgumentParser(prog="python -m reference_perception.train",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=models_dir() / "reference")
    ap.add_argument("--only", nargs="*", choices=PARTS, default=list(PARTS))
    ap.add_argument("--heads", type=int, default=2)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    def log(*x):
        print(*x, flush=True)
    quality_path = a.out / "quality.json"
    quality = json.loads(quality_path.read_text()) if quality_path.exists() else {}
    t_all = time.monotonic()
    if "segmenter" in a.only:
        from .segmenter import DEFAULT_MODEL_PATH, evaluate_segmenter, train_segmenter

        log("== segmenter ==")
        path = a.out / DEFAULT_MODEL_PATH.name
        train_segmenter(path, test_split=None)
        r = evaluate_segmenter(path, "reference_test", verbose=True)
        quality["segmenter"] = {k: r[k] for k in ("miou", "accuracy", "per_class_iou", "ms_per_frame")}
    if "detector" in a.only:
        from .detector import evaluate_detector, train_detector

        log("== detector ==")
        train_detector(a.out, log=log)
        r = evaluate_detector(a.out, log=log)
        quality["detector"] = jsonable(r)
    if "multihead" in a.only:
        from .multihead import evaluate_multihead, train_multihead

        log(f"== multi-head detector ({a.heads} heads) ==")
        train_multihead(a.out, num_heads=a.heads, log=log)
        r = evaluate_multihead(a.out, log=log)
        quality["multihead"] = jsonable(r)
    quality_path.write_text(json.dumps(quality, indent=2, sort_keys=True) + "\n")
    log(f"done in {time.monotonic() - t_all:.0f} s; figures in {quality_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
