"""lidar_quality_tools.load_test: memory growth, output matching by stamp, the rate ladder;
plus a short run of bench/bench_e2e.py's experiment with mimo_node alone (process, frames
over DDS, figures present; no timing asserted: the machine may be loaded)."""
import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pytest
from lidar_quality_tools import fuzz, load_test
from lidar_quality_tools.fuzz import DETECTIONS, FrameTemplate, InputSpec

ROOT = Path(__file__).resolve().parents[2]


def test_memory_growth_after_warmup():
    t = np.arange(0.0, 100.0)
    kb = np.where(t < 20, 100_000 + 5000 * t, 200_000.0)  # grows during warm-up only
    kb[-10:] = 210_000.0
    m = load_test.memory_growth(t, kb, warmup_s=30.0, window_s=5.0)
    assert m["samples"] == 100
    assert m["rss_warm_mb"] == pytest.approx(200_000 / 1024, abs=0.1)
    assert m["rss_end_mb"] == pytest.approx(210_000 / 1024, abs=0.1)
    assert m["growth_pct"] == pytest.approx(5.0)
    assert m["growth_second_half_pct"] == pytest.approx(5.0)  # the step is at the very end
    ramp = load_test.memory_growth(t, 100_000 + 1000 * t, warmup_s=20.0, window_s=4.0)
    # medians of t = 96..99 (end) and t = 58..61 (the middle of 20..99)
    assert ramp["growth_second_half_pct"] == pytest.approx(38_000 / 159_500 * 100, abs=0.01)
    assert m["rss_max_mb"] == pytest.approx(210_000 / 1024, abs=0.1)
    assert m["slope_mb_per_min"] > 0
    assert load_test.memory_growth(t[:5], kb[:5], warmup_s=30.0, window_s=5.0) == {"samples": 5}


def test_process_figures_of_this_process():
    assert load_test.rss_kb(os.getpid()) > 1000
    assert load_test.cpu_seconds(os.getpid()) > 0
    assert load_test.rss_kb(2**22 + 12345) is None  # above pid_max: no such process


def test_thread_cpu_by_kind():
    import threading

    from lidar_quality_ros.threads import name_os_thread

    burnt, done = threading.Event(), threading.Event()

    def burn():
        name_os_thread("lq_testburn")
        t0 = load_test.time.thread_time()
        while load_test.time.thread_time() - t0 < 0.2:
            pass
        burnt.set()
        done.wait(10)  # alive (and listed) while we look

    t = threading.Thread(target=burn)
    t.start()
    burnt.wait(10)
    seen = load_test.thread_cpu_seconds(os.getpid())
    done.set()
    t.join()
    # (other tests' in-process nodes may have left lq_ threads of their own here)
    assert seen.get("lq_testburn", 0) > 0
    assert all(k in ("other", "dds") or k.startswith("lq_") for k in seen)
    assert load_test.thread_cpu_seconds(2**22 + 12345) == {}
    per = load_test._per_frame([(0.0, {"lq_frames": 1.0}), (10.0, {"lq_frames": 1.5,
                                                                   "dds": 0.1})], 10.0)
    assert per == {"dds": 1.0, "lq_frames": 5.0}


def test_output_log_matches_by_stamp():
    t = FrameTemplate([InputSpec("input/detections", DETECTIONS)], n_points=200, n_objects=3,
                      n_proposals=5)
    data = t.serialized("input/detections")
    log = load_test.OutputLog()
    for ns in (5 * 10**9 + 7, 6 * 10**9, 5 * 10**9 + 7):
        log(fuzz.restamp_bytes(data, ns))
    assert set(log.snapshot()) == {5 * 10**9 + 7, 6 * 10**9}
    assert log.duplicates == 1
    assert log.count([6 * 10**9, 7 * 10**9]) == 1


def test_rate_ladder_stops_at_the_first_failure():
    seen = []

    def trial(hz):
        seen.append(hz)
        return hz <= 20, "ok" if hz <= 20 else "3 dropped", {"latency_ms_p99": hz}
    best, steps = load_test.max_sustained_rate(trial, (10, 15, 20, 30, 40))
    assert best == 20 and seen == [10, 15, 20, 30]
    assert [s["ok"] for s in steps] == [True, True, True, False]
    assert steps[-1]["why"] == "3 dropped" and steps[-1]["latency_ms_p99"] == 30
    assert load_test.max_sustained_rate(lambda hz: (False, "x", {}), (10, 20))[0] == 0.0


def test_step_ok_needs_no_drop_and_the_rate():
    def run(dropped=0, achieved=20.0, alive=True):
        return {"rate_hz": 20.0, "achieved_rate_hz": achieved,
                "nodes": {"lmd": {"dropped": dropped, "alive": alive}}}
    assert load_test.step_ok(run(), "lmd") == (True, "ok")
    assert not load_test.step_ok(run(dropped=1), "lmd")[0]
    assert not load_test.step_ok(run(alive=False), "lmd")[0]
    ok, why = load_test.step_ok(run(achieved=15.0), "lmd")
    assert not ok and "publisher" in why


def test_unknown_node_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown node"):
        load_test.LoadTest(["lmd", "nope"], tmp_path)


def test_e2e_experiment_short(tmp_path):
    """bench_e2e's experiment, tiny: mimo_node alone, 3 s together-runs (as deployed, with
    its realtime_priority and the recorder's; with the recorder at normal priority; with
    normal scheduling for all), two 2-s rate steps. The node
    answers over DDS, the figures and the report are there, it exits cleanly."""
    spec = importlib.util.spec_from_file_location("bench_e2e", ROOT / "bench" / "bench_e2e.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    figs, report = bench.experiment(names=("mimo",), duration=3.0, warmup=0.0, rates=(10, 20),
                                    window=2.0, out_dir=tmp_path, n_points=5000)
    by_thread = {k.rsplit(".", 1)[1]: v for k, v in figs.items()
                 if k.startswith("e2e.mimo.cpu_ms_per_frame.")}
    assert set(figs) - {f"e2e.mimo.cpu_ms_per_frame.{k}" for k in by_thread} == {
        f"e2e.mimo.{k}" for k in ("latency_ms_p50", "latency_ms_p99", "dropped", "max_rate_hz",
                                  "cpu_ms_per_frame")} | {
        f"e2e.{run}.mimo.{k}" for run in ("normal_consumer", "normal_sched")
        for k in ("latency_ms_p50", "latency_ms_p99", "dropped")}
    # the node names its threads: the input thread and the frame worker are told apart,
    # and the kinds add up to the process (thread CPU is counted in 10 ms ticks)
    assert set(by_thread) <= {"inputs", "frames", "executor", "dds", "other"}
    assert {"inputs", "frames"} <= set(by_thread)
    assert abs(sum(by_thread.values()) - figs["e2e.mimo.cpu_ms_per_frame"]) <= (
        0.5 + 0.2 * figs["e2e.mimo.cpu_ms_per_frame"])
    # the node's process CPU time per frame: positive, and below a whole 100 ms period
    # times the two cores (a sanity bound on the unit, not a speed assertion)
    assert 0 < figs["e2e.mimo.cpu_ms_per_frame"] < 200
    e = report["together"]["nodes"]["mimo"]
    assert e["published"] == 30 and 0 < e["received"] <= 30
    assert e["dropped"] == 30 - e["received"] == figs["e2e.mimo.dropped"]
    assert e["unexpected_outputs"] == 0 and e["duplicates"] == 0
    assert e["latency_ms_p50"] > 0 and e["memory"]["samples"] >= 2
    assert report["together"]["exit_codes"] == {"mimo": 0}
    # the deployment's priority, granted or said to be refused; then normal scheduling
    assert e["scheduling"] in ("SCHED_FIFO 10", "normal (realtime_priority refused)")
    # the recorder, the outputs' consumer, at the same priority (or said to be refused)
    rec = report["together"]["recorder_scheduling"]
    assert rec == "SCHED_FIFO 10" or rec.startswith("normal (refused: SCHED_FIFO priority 10")
    e = report["together_normal_consumer"]["nodes"]["mimo"]
    assert report["together_normal_consumer"]["recorder_scheduling"] == "normal"
    assert e["scheduling"] == report["together"]["nodes"]["mimo"]["scheduling"]
    assert e["dropped"] == figs["e2e.normal_consumer.mimo.dropped"] and e["published"] == 30
    e = report["together_normal_sched"]["nodes"]["mimo"]
    assert e["scheduling"] == "normal" and e["published"] == 30
    assert report["together_normal_sched"]["recorder_scheduling"] == "normal"
    assert e["dropped"] == figs["e2e.normal_sched.mimo.dropped"]
    assert report["together_normal_sched"]["exit_codes"] == {"mimo": 0}
    steps = report["max_rate"]["mimo"]["steps"]
    assert 1 <= len(steps) <= 2 and steps[0]["rate_hz"] == 10
    assert figs["e2e.mimo.max_rate_hz"] in (0.0, 10.0, 20.0)
    assert report["max_rate"]["mimo"]["exit_code"] == 0
    saved = json.loads((tmp_path / "report.json").read_text())
    assert saved["figures"] == figs
    assert (tmp_path / "all_mimo_node.log").exists()
    assert (tmp_path / "all_normal_sched_mimo_node.log").exists()
