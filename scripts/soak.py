#!/usr/bin/env python3
"""Soak test (issue 8): lmd_node, lms_node and mimo_node at once, 10 Hz, 120k-point frames.

A thin CLI over ``lidar_quality_tools.load_test.LoadTest`` (node processes with their
installed config, pre-serialized synthetic frames over loopback DDS in a private domain;
see that module). After the pre-roll, frames are published at ``--rate`` for
``--duration`` seconds. Reported per node: frames published and received on its main
output (dropped = the difference; the node's own /diagnostics counters beside it),
latency publication -> reception, resident memory (VmRSS, sampled every second) at the
end of the warm-up and at the end, its growth in % (and over the second half of the time
after warm-up: a leak grows in both halves, an allocator settling into its high-water
mark mostly in the first), and CPU use. The run passes with no
dropped frame, RSS growth below ``--max-growth`` % and a clean exit of every node on
SIGINT.

    bash scripts/with_env.sh python scripts/soak.py                   # 10 min (make soak)
    bash scripts/with_env.sh python scripts/soak.py --duration 20 --nodes lmd
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from lidar_quality_tools.load_test import NODES, LoadTest

ROOT = Path(__file__).resolve().parents[1]


def run(names: list[str], duration: float, rate: float, n_points: int, out: Path,
        n_frames: int = 4, warmup: float | None = None, extra_args: dict | None = None) -> dict:
    warmup = min(60.0, duration / 4) if warmup is None else warmup
    lt = LoadTest(names, out.parent, n_points=n_points, n_frames=n_frames,
                  extra_params=extra_args, log_prefix="soak_", say=lambda s: print(s, flush=True))
    load_start = os.getloadavg()
    with lt:
        print(f"soak: pre-roll {lt.preroll_frames} frames; running {duration:.0f} s at "
              f"{rate:g} Hz, {n_points} points per cloud", flush=True)
        r = lt.run(duration, rate, warmup=warmup, progress_every=60.0, keep_series=True)
    r.update(n_points=n_points, frame_bytes=lt.frame_bytes(), load_average_start=load_start,
             load_average_end=os.getloadavg(),
             fastdds_profile=os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"))
    for n, code in lt.exit_codes.items():
        r["nodes"][n]["exit_code"] = code
    return r


def passed(r: dict, max_growth: float) -> bool:
    return all(e["dropped"] == 0 and e["exit_code"] == 0
               and e["memory"].get("growth_pct", float("inf")) < max_growth
               for e in r["nodes"].values())


def print_report(r: dict, max_growth: float) -> None:
    nan = float("nan")

    def f(x):
        return nan if x is None else x
    print(f"\nsoak: {r['duration_s']:.0f} s at {r['rate_hz']:g} Hz (achieved "
          f"{f(r['achieved_rate_hz']):.2f}; {r['late_ticks']} ticks late by a period, "
          f"{r['schedule_resets']} stalls skipped), {r['n_points']} "
          f"points per cloud; RSS growth from the end of a {r['warmup_s']:.0f} s warm-up to "
          f"the end (medians over {r['memory_window_s']:.0f} s); load average "
          f"{r['load_average_start'][0]:.1f} -> {r['load_average_end'][0]:.1f}")
    print(f"{'node':5s} {'sent':>6s} {'recv':>6s} {'drop':>5s} {'lat p50':>8s} {'lat p99':>8s} "
          f"{'RSS warm':>9s} {'RSS end':>8s} {'growth':>7s} {'2nd half':>8s} {'MB/min':>7s} "
          f"{'CPU %':>6s} {'exit':>5s}")
    for n, e in r["nodes"].items():
        m = e["memory"]
        print(f"{n:5s} {e['published']:6d} {e['received']:6d} {e['dropped']:5d} "
              f"{f(e['latency_ms_p50']):8.1f} {f(e['latency_ms_p99']):8.1f} "
              f"{m.get('rss_warm_mb', nan):9.1f} {m.get('rss_end_mb', nan):8.1f} "
              f"{m.get('growth_pct', nan):6.2f}% {m.get('growth_second_half_pct', nan):7.2f}% "
              f"{m.get('slope_mb_per_min', nan):7.3f} "
              f"{f(e['cpu_pct']):6.1f} {e['exit_code']!s:>5s}")
    ok = passed(r, max_growth)
    print(f"-> {'PASS' if ok else 'FAIL'} (no drop, RSS growth < {max_growth:g} %, clean exit)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of input")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--points", type=int, default=120_000)
    ap.add_argument("--nodes", default="lmd,lms,mimo")
    ap.add_argument("--frames", type=int, default=4, help="distinct frames, sent in turn")
    ap.add_argument("--warmup", type=float, default=None,
                    help="seconds before the RSS reference (default: min(60, duration / 4))")
    ap.add_argument("--max-growth", type=float, default=5.0, help="RSS growth limit [%%]")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="extra node parameter, e.g. lmd.classifier_path=/x.joblib")
    ap.add_argument("--out", default=str(ROOT / "out" / "soak" / "report.json"))
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.nodes.split(",") if n.strip()]
    if set(names) - set(NODES):
        ap.error(f"unknown node(s); known: {', '.join(NODES)}")
    extra: dict[str, dict] = {}
    for p in args.param:
        key, _, value = p.partition("=")
        node, _, pname = key.partition(".")
        extra.setdefault(node, {})[pname] = value
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    r = run(names, args.duration, args.rate, args.points, out, n_frames=args.frames,
            warmup=args.warmup, extra_args=extra)
    r["passed"] = passed(r, args.max_growth)
    r["max_growth_pct"] = args.max_growth
    out.write_text(json.dumps(r, indent=1) + "\n")
    print_report(r, args.max_growth)
    print(f"wrote {out}")
    return 0 if r["passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
