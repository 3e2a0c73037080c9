"""End-to-end figures over DDS (issue 8): the three nodes as processes, fed 120k-point
frames, latency from publication to reception, drops, largest sustained rate.

One experiment (``lidar_quality_tools.load_test``: the installed node executables with
their installed config, pre-serialized synthetic frames published raw over the loopback
Fast DDS profile, outputs received by a recorder process of their own and matched by
stamp: ``lidar_quality_tools.output_recorder`` says why not in the publishing process), run once by
``bench/run.py`` (item kind ``"figures"``):

1. lmd_node, lms_node and mimo_node at once, 10 Hz, ``DURATION`` = 60 s measured after a
   ``WARMUP`` of 5 s (not counted). Per node (``lmd``, ``lms``, ``mimo``):
   ``e2e.<node>.latency_ms_p50`` / ``_p99`` (from the start of the publication of the
   node's input frame to the reception of its main output: LMD ``output/detections``,
   LMS ``output/segments``, MIMO ``output/detections``; goals p99 <= 30 / 80 / 10 ms) and
   ``e2e.<node>.dropped`` (frames published without output; goal 0 for all three at once),
   ``e2e.<node>.cpu_ms_per_frame`` (the node process's CPU time per frame, all threads)
   and the same by thread, ``e2e.<node>.cpu_ms_per_frame.<kind>``: ``inputs`` (taking
   and decoding the input messages), ``frames`` (the frame's work: features, models,
   outputs, publishing), ``executor`` (rclpy: timers, /diagnostics, parameter services),
   ``dds`` (Fast DDS's own threads), ``other``.
   The nodes run as deployed on two cores (``DEPLOYMENT``): mimo_node, the one with the
   tightest budget (10 ms), with ``realtime_priority`` 10 (SCHED_FIFO for its threads),
   the others with normal scheduling; the recorder, which stands for the consumer of the
   outputs, at the same priority (``RECORDER_PRIORITY``: a consumer at normal priority
   waits for a core behind LMD's and LMS's frames, and that wait made most of MIMO's
   tail; ``output_recorder`` has the figures). With normal scheduling for all, each
   frame's MIMO threads woke into a machine busy with LMD's and LMS's frames and the
   8.6 MB cloud's publication and waited for a core (p99 15-18 ms). What each node and
   the recorder got is in the report (``scheduling``, ``recorder_scheduling``; a refused
   priority is said there and on stderr).
1b. The same nodes with the recorder at normal priority (the measurement before
   2026-12-01), shown beside: ``e2e.normal_consumer.<node>.latency_ms_p50`` / ``_p99`` /
   ``.dropped``.
1c. The same with normal scheduling for all three and the recorder (``realtime_priority``
   0), shown beside: ``e2e.normal_sched.<node>.latency_ms_p50`` / ``_p99`` / ``.dropped``.
2. Each node alone: the rate stepped through ``RATES`` for ``WINDOW`` = 10 s each, until a
   step drops a frame (or the publisher cannot keep the rate: then the figure is a lower
   bound, the report says so); ``e2e.<node>.max_rate_hz`` = the highest rate with no
   dropped frame (0: not even 10 Hz).

The whole report (every step's latency, the publisher's timing, the nodes' own
diagnostics, CPU and memory) goes to ``out/bench/e2e/report.json``, node logs beside it.
About 9 minutes on the 2-core machine. As a CLI, shorter variants::

    bash scripts/with_env.sh python bench/bench_e2e.py --duration 15 --window 5 --rates 10,20
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("lmd", "lms", "mimo")
DURATION = 60.0
WARMUP = 5.0
RATE = 10.0
RATES = (10, 15, 20, 30, 40, 60, 80, 100)
WINDOW = 10.0
OUT = ROOT / "out" / "bench" / "e2e"
#: issue 8's goals: latency p99 [ms] per node, no dropped frame at 10 Hz with all three
GOALS_P99_MS = {"lmd": 30.0, "lms": 80.0, "mimo": 10.0}
#: per node, the parameters of the two-core deployment measured in part 1 (module doc)
DEPLOYMENT = {"mimo": {"realtime_priority": 10}}
#: SCHED_FIFO priority of the recorder (the outputs' consumer) in the deployment (module doc)
RECORDER_PRIORITY = 10


def _say(s: str) -> None:
    print(f"  [e2e] {s}", file=sys.stderr, flush=True)


def experiment(names=NAMES, duration=DURATION, warmup=WARMUP, rate=RATE, rates=RATES,
               window=WINDOW, out_dir: Path = OUT, n_points: int = 120_000) -> tuple[dict, dict]:
    """Run both parts; returns (figures, report)."""
    from lidar_quality_tools.load_test import LoadTest, max_sustained_rate, step_ok

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    figures: dict[str, float] = {}
    report: dict = {"n_points": n_points, "load_average_start": os.getloadavg(),
                    "fastdds_profile": os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE")}

    # 1. all nodes at once, as deployed; 1b. the consumer at normal priority; 1c. all normal
    for key, params, rec_prio, log_prefix, prefix in (
            ("together", DEPLOYMENT, RECORDER_PRIORITY, "all_", "e2e"),
            ("together_normal_consumer", DEPLOYMENT, 0, "all_normal_consumer_",
             "e2e.normal_consumer"),
            ("together_normal_sched", {}, 0, "all_normal_sched_", "e2e.normal_sched")):
        with LoadTest(names, out_dir, n_points=n_points, log_prefix=log_prefix, say=_say,
                      extra_params={n: p for n, p in params.items() if n in names},
                      recorder_priority=rec_prio) as lt:
            if warmup > 0:
                lt.run(warmup, rate)
            _say(f"{', '.join(names)} at once ({key}): {duration:.0f} s at {rate:g} Hz")
            r = lt.run(duration, rate, progress_every=30.0)
            r["frame_bytes"] = lt.frame_bytes()
        r["exit_codes"] = dict(lt.exit_codes)
        report[key] = r
        if rec_prio and not str(r["recorder_scheduling"]).startswith("SCHED_FIFO"):
            _say(f"WARNING: the recorder's priority {rec_prio} was refused on this machine "
                 f"({r['recorder_scheduling']}): its latencies are with a normal-priority "
                 "consumer")
        for n, e in r["nodes"].items():
            figures[f"{prefix}.{n}.latency_ms_p50"] = e["latency_ms_p50"]
            figures[f"{prefix}.{n}.latency_ms_p99"] = e["latency_ms_p99"]
            figures[f"{prefix}.{n}.dropped"] = e["dropped"]
            if key == "together":
                figures[f"e2e.{n}.cpu_ms_per_frame"] = e["cpu_ms_per_frame"]
                for kind, ms in e["cpu_ms_per_frame_by_thread"].items():
                    figures[f"e2e.{n}.cpu_ms_per_frame.{kind.removeprefix('lq_')}"] = ms
            wanted = params.get(n, {}).get("realtime_priority", 0)
            if wanted and not str(e["scheduling"]).startswith("SCHED_FIFO"):
                _say(f"WARNING: {n}_node's realtime_priority {wanted} was refused on this "
                     f"machine ({e['scheduling']}): its figures are with normal scheduling")
            _say(f"{n} [{e['scheduling']}]: {e['received']}/{e['published']} received, "
                 f"latency p50 {e['latency_ms_p50']} ms p99 {e['latency_ms_p99']} ms (node "
                 f"processing p50 {e['processing_ms_p50']} p99 {e['processing_ms_p99']} ms), "
                 f"CPU {e['cpu_pct']} % = {e['cpu_ms_per_frame']} ms per frame")

    # 2. each node alone, stepping the rate
    report["max_rate"] = {}
    for n in names:
        with LoadTest([n], out_dir, n_points=n_points, log_prefix=f"rate_{n}_", say=_say) as lt:
            def trial(hz, lt=lt, n=n):
                r = lt.run(window, hz, names=[n])
                ok, why = step_ok(r, n)
                e = r["nodes"][n]
                _say(f"{n} alone at {hz:g} Hz for {window:g} s: {why} (latency p50 "
                     f"{e['latency_ms_p50']} p99 {e['latency_ms_p99']} ms, achieved "
                     f"{r['achieved_rate_hz']} Hz)")
                keep = ("published", "received", "dropped", "latency_ms_p50",
                        "latency_ms_p99", "processing_ms_p50", "processing_ms_p99",
                        "diag_dropped_reasons", "cpu_pct", "cpu_ms_per_frame",
                        "cpu_ms_per_frame_by_thread")
                return ok, why, {"achieved_rate_hz": r["achieved_rate_hz"],
                                 "late_ticks": r["late_ticks"], **{k: e[k] for k in keep}}
            best, steps = max_sustained_rate(trial, rates)
        last = steps[-1] if steps else {}
        report["max_rate"][n] = {
            "max_rate_hz": best, "window_s": window, "steps": steps,
            "exit_code": lt.exit_codes.get(n),
            "lower_bound": bool(last.get("ok")) or "publisher" in str(last.get("why", "")),
        }
        figures[f"e2e.{n}.max_rate_hz"] = best
    report["goals"] = {n: {"latency_ms_p99_goal": GOALS_P99_MS[n],
                           "latency_met": (figures[f"e2e.{n}.latency_ms_p99"] or 1e9)
                           <= GOALS_P99_MS[n],
                           "no_drop": figures[f"e2e.{n}.dropped"] == 0}
                       for n in names}
    report["load_average_end"] = os.getloadavg()
    report["elapsed_s"] = round(time.monotonic() - t_start, 1)
    report["figures"] = figures
    (out_dir / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    _say(f"wrote {out_dir / 'report.json'} ({report['elapsed_s']:.0f} s)")
    return figures, report


def figures():
    yield "e2e", lambda: experiment()[0], "figures"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", default=",".join(NAMES))
    ap.add_argument("--duration", type=float, default=DURATION,
                    help="seconds of the all-nodes run")
    ap.add_argument("--warmup", type=float, default=WARMUP)
    ap.add_argument("--rate", type=float, default=RATE)
    ap.add_argument("--rates", default=",".join(map(str, RATES)),
                    help="rates stepped through per node alone ('' : skip)")
    ap.add_argument("--window", type=float, default=WINDOW, help="seconds per rate step")
    ap.add_argument("--points", type=int, default=120_000)
    ap.add_argument("--out", default=str(OUT), help="directory of report.json and node logs")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.nodes.split(",") if n.strip()]
    rates = [float(x) for x in args.rates.split(",") if x.strip()]
    figs, report = experiment(names, args.duration, args.warmup, args.rate, rates,
                              args.window, Path(args.out), args.points)
    for k, v in figs.items():
        print(f"{k:32s} {v}")
    for n, g in report["goals"].items():
        print(f"{n}: p99 <= {g['latency_ms_p99_goal']:g} ms "
              f"{'met' if g['latency_met'] else 'NOT met'}; no drop at {args.rate:g} Hz with "
              f"{', '.join(names)} at once: {'met' if g['no_drop'] else 'NOT met'}")
    together = report["together"]["nodes"]
    ok = all(e["alive"] for e in together.values()) and all(
        c == 0 for c in report["together"]["exit_codes"].values())
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
