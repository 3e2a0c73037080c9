"""The demo end to end on a 5-frame perception bag: node executables as processes with
use_sim_time, bag_player replaying with /clock, outputs recorded and evaluated; the
report, summary and plots written. And a bag that is not a perception bag: a clear
failure, no hang."""
import json
import subprocess
import sys

import pytest
from lidar_quality_ros.bag_io import bag_info
from lidar_quality_ros.load_test import NODES
from perception_bags import simulated_perception_bags
from reference_perception.cli import Perception

N_FRAMES = 5


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return simulated_perception_bags(tmp_path_factory.mktemp("demo"), Perception(heads=2),
                                     n_sequences=1, n_frames=N_FRAMES, seed=11, columns=512)


def demo(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lidar_quality_tools.demo", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def test_demo_end_to_end(bags, tmp_path):
    out = tmp_path / "demo"
    r = demo("--bag", bags, "--out", out)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    keys = {"frames_in", "frames_out", "dropped", "latency_ms_p50", "latency_ms_p99", "auroc",
            "auroc_baseline", "ece", "ece_baseline", "r2"}
    for node in ("lmd", "lms", "mimo"):
        v = s["nodes"][node]
        assert keys <= set(v), node
        assert v["frames_in"] == N_FRAMES and 0 < v["frames_out"] <= N_FRAMES
        assert v["dropped"] == v["frames_in"] - v["frames_out"]
        assert v["exit_code"] == 0 and v["mismatched"] == 0
        assert v["latency_ms_p50"] > 0 and v["n"] > 0
        assert node in r.stdout
    # every main output recorded once per processed frame, with the input's stamps
    info = bag_info(out / "outputs")
    for node, (_, main) in NODES.items():
        assert info.topics[f"/{node}/{main}"].count == s["nodes"][node]["frames_out"]
    for png in ("lmd_reliability", "lms_iou_scatter", "mimo_reliability", "lmd_bev_frame",
                "lms_segmentation_frame", "latency"):
        assert (out / f"{png}.png").stat().st_size > 1000, png
        assert f"({png}.png)" in (out / "report.md").read_text()


def test_not_a_perception_bag(bags, tmp_path):
    sim_bag = bags.parent / "sim_00"   # the simulator's bag: no detector outputs
    r = demo("--bag", sim_bag, "--out", tmp_path / "demo", timeout=120)
    assert r.returncode != 0
    assert "not a perception bag" in r.stderr + r.stdout
    r = demo("--bag", tmp_path / "nowhere", "--out", tmp_path / "demo", timeout=120)
    assert r.returncode == 2 and "no perception bag" in r.stderr
