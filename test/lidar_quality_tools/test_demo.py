"""The demo end to end on a 5-frame perception bag: node executables as processes with
use_sim_time, bag_player replaying with /clock, outputs recorded and evaluated; the
report, summary and plots written. A bag whose middle cloud is malformed: LMD and LMS
drop that frame, the demo says so first and exits 4, the pictures come from a frame
every node answered; the exit-code decision on that run's figures. And a bag that is not
a perception bag: a clear failure, no hang."""
import copy
import json
import subprocess
import sys

import pytest
from lidar_quality_ros.bag_io import BagWriter, bag_info, read_bag
from lidar_quality_tools.load_test import NODES
from lidar_quality_tools.demo import EXIT_DROPPED, EXIT_FAILED, EXIT_OK, verdict
from perception_bags import simulated_perception_bags
from rclpy.serialization import deserialize_message, serialize_message
from reference_perception.cli import Perception
from sensor_msgs.msg import PointCloud2

N_FRAMES = 5


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return simulated_perception_bags(tmp_path_factory.mktemp("demo"), Perception(heads=2),
                                     n_sequences=1, n_frames=N_FRAMES, seed=11, columns=512)


def demo(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "lidar_quality_tools.demo", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def table_line(stdout: str) -> int:
    return next(i for i, line in enumerate(stdout.splitlines()) if line.startswith("node "))


@pytest.fixture(scope="module")
def vision_run(bags, tmp_path_factory):
    out = tmp_path_factory.mktemp("vision") / "demo"
    return demo("--bag", bags, "--out", out, "--rate", 0.5), out   # half speed: drops unlikely


def test_demo_end_to_end(vision_run):
    r, out = vision_run
    s = json.loads((out / "summary.json").read_text())
    # 0 unless a node dropped a frame on a loaded machine: then 3, said first
    dropped = [n for n, v in s["nodes"].items() if v["dropped"]]
    assert r.returncode == (EXIT_DROPPED if dropped else EXIT_OK), r.stdout + r.stderr
    head = r.stdout.splitlines()[:table_line(r.stdout)]   # the verdict before the table
    for n in dropped:
        assert any(x.startswith(f"demo: FRAMES DROPPED: {n}_node dropped "
                                f"{s['nodes'][n]['dropped']} of {N_FRAMES} frames")
                   for x in head), head
    if not dropped:
        assert any(x.startswith("demo: OK: ") for x in head), head
    assert s["verdict"]["picture_frame"] is not None
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
    # every process's CPU per frame, and their total, measured and printed
    cpu = s["cpu_ms_per_frame"]
    assert set(cpu) == {"player", "lmd", "lms", "mimo", "recorder", "total"}
    assert all(v > 0 for v in cpu.values()), cpu
    assert abs(cpu["total"] - sum(v for n, v in cpu.items() if n != "total")) < 0.5
    assert any(x.startswith("demo: CPU per frame [ms]: player ") for x in head), head
    assert s["sync_s"] >= 0  # written pages flushed before the real-time replay
    # the player's schedule shifts (max_lateness: stalls delay, never burst) are reported
    assert s["player"]["shifts"] >= 0 and s["player"]["shifted_ms"] >= 0
    assert (s["player"]["shifts"] > 0) == any("the player stalled" in x for x in head)
    # every main output recorded once per processed frame, with the input's stamps
    info = bag_info(out / "outputs")
    for node, (_, main) in NODES.items():
        assert info.topics[f"/{node}/{main}"].count == s["nodes"][node]["frames_out"]
    for png in ("lmd_reliability", "lms_iou_scatter", "mimo_reliability", "lmd_bev_frame",
                "lms_segmentation_frame", "latency"):
        assert (out / f"{png}.png").stat().st_size > 1000, png
        assert f"({png}.png)" in (out / "report.md").read_text()


def test_demo_in_autoware_mode_gives_the_same_quality(bags, vision_run, tmp_path):
    """Acceptance (issue 19): make demo AUTOWARE=1: the bag's detections converted once to
    DetectedObjects (beside it), LMD and MIMO reading and writing them, the same quality
    figures as the vision_msgs run (scores travel as float32 there)."""
    out = tmp_path / "demo_autoware"
    r = demo("--bag", bags, "--out", out, "--rate", 0.5, "--autoware")
    s = json.loads((out / "summary.json").read_text())
    assert r.returncode in (EXIT_OK, EXIT_DROPPED), r.stdout + r.stderr
    assert s["mode"] == "autoware" and "Autoware DetectedObjects" in r.stdout
    twin = bags.parent / f"{bags.name}_autoware" / "seq_00"
    assert s["played"] == str(twin)
    assert bag_info(twin).topics["/perception/head_0"].msgtype == \
        "autoware_perception_msgs/msg/DetectedObjects"
    info = bag_info(out / "outputs")
    vision = json.loads((vision_run[1] / "summary.json").read_text())
    for node in ("lmd", "mimo"):
        v, w = s["nodes"][node], vision["nodes"][node]
        assert v["mismatched"] == 0 and v["frames_out"] > 0, v
        assert info.topics[f"/{node}/output/objects"].count == v["frames_out"]
        if v["frames_out"] == w["frames_out"] == N_FRAMES:  # both answered every frame
            for k in ("n", "auroc", "ece", "r2", "auroc_baseline"):
                assert v[k] == pytest.approx(w[k], abs=1e-4), (node, k, v[k], w[k])


def malformed_middle_cloud(bag, dst):
    """``bag`` with the middle frame's /lidar/points data buffer 7 bytes short."""
    stamps = sorted({m.stamp_ns for m in read_bag(bag, {"/lidar/points"})})
    with BagWriter(dst) as w:
        for m in read_bag(bag):
            raw = m.raw
            if m.topic == "/lidar/points" and m.stamp_ns == stamps[N_FRAMES // 2]:
                msg = deserialize_message(raw, PointCloud2)
                msg.data = bytes(msg.data)[:len(msg.data) - 7]
                raw = serialize_message(msg)
            w.write(m.topic, m.msgtype, m.stamp_ns, raw)


@pytest.fixture(scope="module")
def dropped_run(bags, tmp_path_factory):
    """The demo on a bag whose middle cloud LMD and LMS cannot read."""
    root = tmp_path_factory.mktemp("dropped")
    malformed_middle_cloud(bags / "seq_00", root / "seq_00")
    out = root / "demo"
    r = demo("--bag", root / "seq_00", "--out", out, "--rate", 0.5)
    return r, out, json.loads((out / "summary.json").read_text())


def test_dropped_frames_exit_4_and_are_said_first(dropped_run):
    r, out, s = dropped_run
    assert r.returncode == EXIT_DROPPED, r.stdout + r.stderr
    nodes = s["nodes"]
    for n in ("lmd", "lms"):
        assert nodes[n]["dropped"] >= 1 and nodes[n]["exit_code"] == 0
        assert nodes[n]["node_diagnostics"]["dropped.malformed_cloud"] == "1"
    head = r.stdout.splitlines()[:table_line(r.stdout)]   # before the table
    said = [x for x in head if x.startswith("demo: FRAMES DROPPED")]
    assert {x.split()[3] for x in said} >= {"lmd_node", "lms_node"}
    lmd = next(x for x in said if x.split()[3] == "lmd_node")
    assert f"dropped {nodes['lmd']['dropped']} of {N_FRAMES} frames" in lmd
    assert "likely cause: " in lmd and "1 frame(s) with a malformed input cloud" in lmd
    assert f"exit 4 (frames dropped: lmd_node {nodes['lmd']['dropped']} of {N_FRAMES}" \
        in r.stderr
    report = (out / "report.md").read_text()
    assert report.index("Exit code 4") < report.index("lmd_node dropped") < report.index(
        "## Frames and latency")
    # the pictures: not the middle frame (LMD and LMS dropped it) but one all answered
    assert s["verdict"]["picture_frame"] not in (None, N_FRAMES // 2)
    assert "the nearest to the middle frame 2 that every node answered" in report
    for png in ("lmd_bev_frame", "lms_segmentation_frame"):
        assert (out / f"{png}.png").stat().st_size > 1000, png
        assert f"({png}.png)" in report


def test_exit_code_decision_on_the_recorded_run(dropped_run):
    """``verdict`` on the figures of a real run: LMD and LMS dropped 1 of 5 frames (20 %)."""
    _, _, s = dropped_run
    nodes = s["nodes"]
    worst = max(v["dropped"] / v["frames_in"] for v in nodes.values())
    assert verdict(nodes)[0] == EXIT_DROPPED
    code, lines = verdict(nodes, max_drop_fraction=worst)      # at the limit: passes
    assert code == EXIT_OK and lines[-1].startswith("OK: no node dropped more than")
    assert any(x.startswith("note: lmd_node dropped") and "malformed" in x for x in lines)
    assert verdict(nodes, max_drop_fraction=0.19)[0] == EXIT_DROPPED
    dead = copy.deepcopy(nodes)
    dead["mimo"]["exit_code"] = -11                             # a crash comes before drops
    code, lines = verdict(dead)
    assert code == EXIT_FAILED and lines[0].startswith("FAILED: mimo_node exited with -11")


def test_likely_cause_from_the_node_diagnostics(dropped_run):
    """On MIMO's recorded figures with its drop counters zeroed, as if 2 frames had been
    lost: processing slower than the input period is named, with the node's own times;
    messages the node did not receive, and outputs the recorder did not, are named too.
    (Zeroed: MIMO drops nothing here as a rule, but once in a clean-clone CI run its first
    frame stalled 0.68 s on the loaded machine and the next ones overran.)"""
    from lidar_quality_tools.demo import likely_causes

    mimo = copy.deepcopy(dropped_run[2]["nodes"]["mimo"])
    d = mimo["node_diagnostics"]
    d.update({k: "0" for k in d if k == "dropped" or k.startswith("dropped.")})
    n = mimo["frames_in"] = mimo["frames_out"] = int(d["frames_out"])  # as the node saw it
    for key, inp in mimo["inputs"].items():
        inp["published"] = int(d[f"received.{key}"])
    p99 = float(d["processing_ms_p99"])
    assert likely_causes(mimo, p99 * 2) == [
        f"none in the node's diagnostics (see {mimo['log']})"]
    mimo["frames_out"] -= 2
    cpu = likely_causes(mimo, p99 / 2)
    assert cpu[0].startswith(f"CPU: processing p50 {float(d['processing_ms_p50']):.0f} ms / "
                             f"p99 {p99:.0f} ms against an input period of {p99 / 2:.0f} ms")
    d["received.input/head_1"] = str(mimo["inputs"]["input/head_1"]["published"] - 2)
    causes = likely_causes(mimo, p99 * 2)
    assert causes[0] == (f"input lost on the way: received {d['received.input/head_1']} of "
                         f"{mimo['inputs']['input/head_1']['published']} on /perception/head_1")
    assert causes[1] == (f"outputs lost on the way: the node published {n}, the recorder "
                         f"received {n - 2}")
    d["sync.dropped.input/head_0"] = "1"
    assert likely_causes(mimo, p99 * 2)[1] == (
        "stamp matching: message(s) dropped (1 on input/head_0): a frame's inputs came too "
        "late or not at all")


def test_not_a_perception_bag(bags, tmp_path):
    sim_bag = bags.parent / "sim_00"   # the simulator's bag: no detector outputs
    r = demo("--bag", sim_bag, "--out", tmp_path / "demo", timeout=120)
    assert r.returncode != 0
    assert "not a perception bag" in r.stderr + r.stdout
    r = demo("--bag", tmp_path / "nowhere", "--out", tmp_path / "demo", timeout=120)
    assert r.returncode == 2 and "no perception bag" in r.stderr
