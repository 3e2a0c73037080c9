"""Benchmark runner: ``python bench/run.py [--out FILE] [--only PREFIX] [--reps N]``.

Every ``bench/bench_*.py`` module exposes ``figures()``, a generator of items:

* ``(name, fn)``: set-up done before the yield, ``fn()`` = one repetition; the figure is
  the median over ``reps`` timed repetitions, in ms;
* ``(name, fn, "percentiles")``: the same, reported as ``name_p50`` / ``name_p99``;
* ``(name, fn, "figures")``: a whole experiment (e.g. ``bench_e2e``): ``fn()`` runs once,
  untimed, and returns ``{figure name: value}``, each name starting with ``name.``.

``--only PREFIX`` runs the items whose name starts with it (an experiment also when the
prefix starts with its name, keeping only the figures that match).

The runner sets the node executables' allocator policy first
(``lidar_quality_ros.threads.keep_freed_memory``), so that the in-process frame figures
are what a node process spends on a frame.
"""
from __future__ import annotations

import argparse
import gc
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def time_fn(fn, reps: int, warmup: int = 3) -> np.ndarray:
    """Wall time of ``reps`` calls of ``fn`` in milliseconds (GC paused while timing)."""
    for _ in range(warmup):
        fn()
    out = np.empty(reps)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for i in range(reps):
            t0 = time.perf_counter()
            fn()
            out[i] = (time.perf_counter() - t0) * 1e3
    finally:
        if gc_was:
            gc.enable()
    return out


#: figures also stated as a multiple of the floor: one copy of a 120k-point cloud
RATIO_TO_COPY = ("core.points_in_boxes_120k_550_ms", "lms.metrics_ms_p50")
BASELINE = "baseline.copy_cloud_120k_ms"


def copy_ratios(results: dict) -> dict:
    """``ratio.<figure>_to_copy`` for the ``RATIO_TO_COPY`` figures present."""
    base = results.get(BASELINE)
    if not base:
        return {}
    return {f"ratio.{n.removesuffix('_ms').removesuffix('_ms_p50')}_to_copy":
            round(results[n] / base, 1) for n in RATIO_TO_COPY if results.get(n) is not None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench/results.json")
    ap.add_argument("--only", default="", help="run only figures whose name starts with this")
    ap.add_argument("--reps", type=int, default=100)
    args = ap.parse_args(argv)
    from lidar_quality_ros.threads import keep_freed_memory
    keep_freed_memory()  # as in the node processes (lidar_quality_ros.runner.run_node)
    results: dict[str, float] = {}
    for path in sorted(HERE.glob("bench_*.py")):
        for item in _load(path).figures():
            name, fn = item[0], item[1]
            kind = item[2] if len(item) > 2 else "median"
            if kind == "figures":
                if not (name.startswith(args.only) or args.only.startswith(name)):
                    continue
                t0 = time.perf_counter()
                figs = {k: v for k, v in fn().items() if k.startswith(args.only)}
                results.update(figs)
                for k, v in figs.items():
                    print(f"{k:45s} {v}", flush=True)
                print(f"{name:45s} ({time.perf_counter() - t0:.0f} s)", flush=True)
                continue
            if not name.startswith(args.only):
                continue
            t = time_fn(fn, max(args.reps, 50))
            if kind == "percentiles":
                results[f"{name}_p50"] = round(float(np.percentile(t, 50)), 4)
                results[f"{name}_p99"] = round(float(np.percentile(t, 99)), 4)
            else:
                results[name] = round(float(np.median(t)), 4)
            print(f"{name:45s} median {np.median(t):9.3f} ms  p99 {np.percentile(t, 99):9.3f} ms",
                  flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(out.read_text()) if out.exists() and args.only else {}
    old.update(results)
    for name, value in copy_ratios(old).items():
        old[name] = value
        print(f"{name:45s} {value} x one copy of a 120k-point cloud", flush=True)
    out.write_text(json.dumps(old, indent=2, sort_keys=True) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
