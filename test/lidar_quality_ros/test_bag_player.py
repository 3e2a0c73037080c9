"""bag_player: real bags (BagWriter) replayed over real rclpy into the test's collectors."""
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from lidar_quality_core.pointcloud import create_xyz_cloud
from lidar_quality_msgs.msg import BoxVariance, BoxVarianceArray
from node_shell_checks import assert_declared_with_descriptions, executable, wait_until
from realbags import REAL_BAGS, humble_metadata, real_bag
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from vision_msgs.msg import Detection3D, Detection3DArray

from lidar_quality_ros.bag_io import BagWriter
from lidar_quality_ros.bag_player import BagPlayer, format_summary, parse_remaps, playback_qos
from lidar_quality_ros.qos import output_qos

T0 = 1_700_000_000 * 10**9
PERIOD = 100_000_000  # 10 Hz
BEST_EFFORT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)


def make_bag(path, frames=10, storage="mcap", qos=None, recorded_clock=False):
    """A 10 Hz bag: /pts clouds, /dets (1 ms after the cloud), /var every other frame.
    Header stamps lag the log times by 50 ms (so log times cannot pass for stamps).
    Returns topic -> list of (log time, message)."""
    qos = qos or {}
    rng = np.random.default_rng(0)
    out = {"/pts": [], "/dets": [], "/var": []}
    with BagWriter(path, storage=storage) as w:
        for i in range(frames):
            log = T0 + i * PERIOD
            h = Header(frame_id="lidar")
            h.stamp.sec, h.stamp.nanosec = divmod(log - 50_000_000, 10**9)
            xyz = rng.normal(size=(200, 3)).astype(np.float32)
            msgs = [("/pts", "sensor_msgs/msg/PointCloud2", log, create_xyz_cloud(h, xyz)),
                    ("/dets", "vision_msgs/msg/Detection3DArray", log + 1_000_000,
                     Detection3DArray(header=h, detections=[Detection3D(id=f"{i}-{k}")
                                                            for k in range(3)]))]
            if i % 2 == 0:
                msgs.append(("/var", "lidar_quality_msgs/msg/BoxVarianceArray", log + 2_000_000,
                             BoxVarianceArray(header=h, variances=[BoxVariance(detection_id=f"{i}-0",
                                                                               yaw=0.1 * i)])))
            if recorded_clock:  # a bogus recorded clock: must not reach /clock
                msgs.append(("/clock", "rosgraph_msgs/msg/Clock", log, Clock()))
            for topic, msgtype, stamp, msg in msgs:
                w.write(topic, msgtype, stamp, msg, qos=qos.get(topic, ()))
                if topic in out:
                    out[topic].append((stamp, msg))
    return out


def collectors(ros, topics, qos=None):
    types = {"/pts": PointCloud2, "/dets": Detection3DArray, "/var": BoxVarianceArray}
    return {t: ros.collector(types[t], t, qos) for t in topics}


def play(ros, bag, **params):
    player = ros.start(BagPlayer, parameters={"bag": str(bag), "wait_for_subscribers": 1, **params})
    assert player.finished.wait(30.0), "playback did not end"
    assert player.error is None
    return player


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_plays_every_topic_in_order_with_original_contents(ros, tmp_path, storage):
    sent = make_bag(tmp_path / "b", storage=storage)
    cols = collectors(ros, sent)
    player = play(ros, tmp_path / "b")
    for topic, col in cols.items():
        assert col.wait_for(len(sent[topic]), timeout=10.0), topic
        # same messages (header stamps included), same order, nothing extra
        assert col.messages == [m for _, m in sent[topic]], topic
    summary = player.summary()
    assert {t: v["count"] for t, v in summary["topics"].items()} == {"/pts": 10, "/dets": 10, "/var": 5}
    assert summary["messages"] == 25 and summary["passes"] == 1
    assert summary["cpu_s"] > 0      # the process's CPU time from the first to the last publish


def test_clock_follows_log_times_and_recorded_clock_is_not_replayed(ros, tmp_path):
    sent = make_bag(tmp_path / "b", recorded_clock=True)
    clock = ros.collector(Clock, "/clock")
    cols = collectors(ros, sent)
    play(ros, tmp_path / "b", clock_rate=50.0)
    assert cols["/pts"].wait_for(10, timeout=10.0)
    assert wait_until(lambda: any(_ns(c) == sent["/dets"][-1][0] for c in clock.messages), 5.0)
    values = [_ns(c) for c in clock.messages]
    assert all(b >= a for a, b in zip(values, values[1:])), "clock went backwards"
    assert values[0] >= T0 and values[-1] == sent["/dets"][-1][0]  # bogus recorded zeros absent
    # one per distinct log time, plus ticks in between (50 Hz over ~1 s while the player
    # waits for the next message; a player running late on a loaded machine waits less,
    # so only their presence is asserted)
    stamps = {s for msgs in sent.values() for s, _ in msgs}
    assert stamps <= set(values)
    ticks = sorted(set(values) - stamps)
    assert ticks and all(T0 < t < sent["/dets"][-1][0] for t in ticks)


def _ns(clock_msg):
    return clock_msg.clock.sec * 10**9 + clock_msg.clock.nanosec


def test_rate_scales_playback_time(ros, tmp_path):
    sent = make_bag(tmp_path / "b", frames=21)  # 2.0 s recorded
    recorded = (sent["/pts"][-1][0] - sent["/pts"][0][0]) / 1e9
    cols = collectors(ros, ["/pts"])
    player = play(ros, tmp_path / "b", rate=2.0, topics="/pts")
    assert cols["/pts"].wait_for(21, timeout=10.0)
    times = cols["/pts"].receive_times
    span = times[-1] - times[0]
    # never early: at least half the recorded span (minus the first message's lateness);
    # at most half of it plus the lateness the player itself reports (a stall of the
    # machine or of this process shows there, not as a wrong schedule), delivery 0.1 s
    summary = player.summary()
    late = summary["late_ms_max"] / 1e3
    assert 0.45 * recorded < span < 0.5 * recorded + late + 0.1, (span, late)
    assert 0.45 * recorded < summary["wall_s"] < 0.5 * recorded + late + 0.1, (summary, late)
    assert 2.0 * 0.5 * recorded / (0.5 * recorded + late + 0.1) < summary["achieved_rate"] < 2.05


def test_remapping_topic_selection_and_exclusion(ros, tmp_path):
    sent = make_bag(tmp_path / "b")
    remapped = ros.collector(PointCloud2, "/remapped/points")
    others = collectors(ros, ["/pts", "/dets", "/var"])
    player = play(ros, tmp_path / "b", topics="/pts, /var", exclude_topics="/var",
                  remap="/pts:=/remapped/points")
    assert remapped.wait_for(10, timeout=10.0)
    assert remapped.messages == [m for _, m in sent["/pts"]]
    published = {t for t, _ in ros.node.get_topic_names_and_types()
                 if any(i.node_name == player.get_name() for i in ros.node.get_publishers_info_by_topic(t))}
    assert published - {"/rosout", "/parameter_events"} == {"/remapped/points", "/clock"}
    assert set(player.summary()["topics"]) == {"/pts"}
    assert all(len(c) == 0 for c in others.values())


def test_unknown_topic_bad_remap_and_missing_bag_refused(ros, tmp_path):
    make_bag(tmp_path / "b", frames=2)
    with pytest.raises(ValueError, match="not in the bag.*'/nope'"):
        ros.start(BagPlayer, parameters={"bag": str(tmp_path / "b"), "topics": "/pts /nope"})
    with pytest.raises(ValueError, match="OLD:=NEW"):
        parse_remaps(["/pts=/x"])
    with pytest.raises(FileNotFoundError, match="bag not found"):
        ros.start(BagPlayer, parameters={"bag": str(tmp_path / "missing")})
    with pytest.raises(ValueError, match="past the end"):
        ros.start(BagPlayer, parameters={"bag": str(tmp_path / "b"), "start_offset": 5.0})


def test_loop_replays_until_stopped(ros, tmp_path):
    sent = make_bag(tmp_path / "b", frames=4)
    cols = collectors(ros, ["/dets"])
    player = ros.start(BagPlayer, parameters={"bag": str(tmp_path / "b"), "loop": True, "rate": 2.0,
                                              "topics": "/dets", "wait_for_subscribers": 1})
    assert cols["/dets"].wait_for(10, timeout=15.0)
    assert not player.finished.is_set()
    player.stop_processing()
    assert player.finished.wait(5.0)
    once = [m for _, m in sent["/dets"]]
    got = cols["/dets"].messages
    assert got == (once * (len(got) // 4 + 1))[:len(got)]  # the bag over and over, in order
    assert player.summary()["passes"] >= 2


def test_start_offset_and_delay(ros, tmp_path):
    sent = make_bag(tmp_path / "b")
    cols = collectors(ros, ["/pts"])
    t = time.monotonic()
    play(ros, tmp_path / "b", start_offset=0.55, delay=0.5, topics="/pts")
    assert cols["/pts"].wait_for(4, timeout=10.0)
    assert cols["/pts"].receive_times[0] - t >= 0.5
    assert cols["/pts"].messages == [m for _, m in sent["/pts"][6:]]  # log times >= T0 + 0.55 s


def test_recorded_qos_and_best_effort_override(ros, tmp_path):
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    make_bag(tmp_path / "b", frames=2,
             qos={"/pts": [qos_profile_sensor_data], "/var": [latched]})
    player = ros.start(BagPlayer, parameters={"bag": str(tmp_path / "b")})
    assert player.finished.wait(10.0)

    def offered(p, topic):
        (info,) = [i for i in ros.node.get_publishers_info_by_topic(topic) if i.node_name == p.get_name()]
        return info.qos_profile

    assert offered(player, "/pts").reliability == ReliabilityPolicy.BEST_EFFORT
    assert offered(player, "/dets").reliability == ReliabilityPolicy.RELIABLE  # none recorded
    assert offered(player, "/var").durability == DurabilityPolicy.TRANSIENT_LOCAL
    p2 = ros.collector(PointCloud2, "/p2", BEST_EFFORT_QOS)
    d2 = ros.collector(Detection3DArray, "/d2")
    forced = play(ros, tmp_path / "b", best_effort="sensor_msgs/msg/*", topics="/pts /dets",
                  remap="/pts:=/p2 /dets:=/d2")
    assert p2.wait_for(2, timeout=10.0) and d2.wait_for(2, timeout=10.0)
    assert offered(forced, "/p2").reliability == ReliabilityPolicy.BEST_EFFORT
    assert offered(forced, "/d2").reliability == ReliabilityPolicy.RELIABLE


def test_playback_qos_adapts_offers():
    rel, be = output_qos(5), QoSProfile(depth=7, reliability=ReliabilityPolicy.BEST_EFFORT)
    assert playback_qos([]).reliability == ReliabilityPolicy.RELIABLE and playback_qos([]).depth == 10
    assert playback_qos([rel, be]).reliability == ReliabilityPolicy.BEST_EFFORT
    assert playback_qos([rel, be]).depth == 7
    assert playback_qos([rel]).durability == DurabilityPolicy.VOLATILE
    assert playback_qos([rel], best_effort=True).reliability == ReliabilityPolicy.BEST_EFFORT
    keep_all = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=0)
    assert playback_qos([keep_all]).history == HistoryPolicy.KEEP_ALL


def test_parameters_have_descriptions(ros, tmp_path):
    make_bag(tmp_path / "b", frames=2)
    player = ros.start(BagPlayer, parameters={"bag": str(tmp_path / "b")})
    assert_declared_with_descriptions(player, {"bag", "topics", "exclude_topics", "remap", "rate",
                                               "loop", "start_offset", "delay", "clock", "clock_rate",
                                               "best_effort", "wait_for_subscribers"})


def test_python_module_plays_to_the_end_with_ros_args(ros, tmp_path):
    sent = make_bag(tmp_path / "b")
    col = ros.collector(Detection3DArray, "/via_ros_args")
    summary = tmp_path / "summary.json"
    proc = ros.spawn([sys.executable, "-m", "lidar_quality_ros.bag_player", str(tmp_path / "b"),
                      "--topics", "/dets", "--wait-for-subscribers", "1", "--summary-json", str(summary),
                      "--ros-args", "-r", "/dets:=/via_ros_args", "-p", "rate:=2.0"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert col.wait_for(10, timeout=5.0) and col.messages == [m for _, m in sent["/dets"]]
    result = json.loads(summary.read_text())
    assert result["topics"]["/dets"]["count"] == 10 and result["rate"] == 2.0
    assert "/via_ros_args" in out and "achieved rate" in out and "Traceback" not in out


def test_publish_log_has_every_message_with_its_publish_time(ros, tmp_path):
    sent = make_bag(tmp_path / "b")
    cols = collectors(ros, sent)
    log = tmp_path / "published.txt"
    before = time.time_ns()
    play(ros, tmp_path / "b", publish_log=str(log))
    after = time.time_ns()
    rows = [line.split() for line in log.read_text().splitlines()]
    assert [(t, int(ns)) for t, ns, _ in rows] == sorted(
        ((t, stamp) for t, ms in sent.items() for stamp, _ in ms), key=lambda r: r[1])
    wall = np.array([int(w) for *_, w in rows])
    assert before < wall[0] and np.all(np.diff(wall) >= 0) and wall[-1] < after
    # never ahead of the recorded schedule (late, on a loaded machine, is possible)
    assert wall[-1] - wall[0] >= int(rows[-1][1]) - int(rows[0][1]) - 1e6
    assert all(c.wait_for(len(sent[t]), timeout=10.0) for t, c in cols.items())


def _stall_player_during_playback(player, seconds):
    """A real stall of the player's threads: this thread keeps the GIL for ``seconds`` once
    a few frames are out (as a long C call or collection would)."""
    assert wait_until(lambda: player.summary()["messages"] >= 6, 10.0)
    old = sys.getswitchinterval()
    sys.setswitchinterval(10.0)
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(old)


@pytest.mark.parametrize("max_lateness", [0.0, 0.03])
def test_a_stall_shifts_the_schedule_instead_of_bursting(ros, tmp_path, max_lateness):
    sent = make_bag(tmp_path / "b", frames=20)
    cols = collectors(ros, ["/pts"])
    log = tmp_path / "published.txt"
    player = ros.start(BagPlayer, parameters={
        "bag": str(tmp_path / "b"), "wait_for_subscribers": 1, "topics": "/pts",
        "max_lateness": max_lateness, "publish_log": str(log)})
    _stall_player_during_playback(player, 0.5)
    assert player.finished.wait(30.0) and player.error is None
    assert cols["/pts"].wait_for(20, timeout=10.0)
    assert [m for m in cols["/pts"].messages] == [m for _, m in sent["/pts"]]
    gaps = np.diff([int(line.split()[2]) for line in log.read_text().splitlines()]) / 1e9
    summary = player.summary()
    if max_lateness:
        # the late frame goes out at once, the next ones a whole period after it: never
        # closer than the period minus the lateness allowed without a shift
        assert gaps.min() >= PERIOD / 1e9 - max_lateness - 1e-3, gaps
        assert summary["shifts"] >= 1 and summary["shifted_ms"] >= 300, summary
        assert "schedule shifted" in format_summary(summary)
        # the achieved rate counts the shift as time lost: 1.9 s of bag in >= 2.2 s
        assert summary["achieved_rate"] < 0.9, summary
    else:  # as ros2 bag play: the frames due during the stall go out back to back
        assert gaps.min() < 0.01, gaps
        assert summary["shifts"] == 0 and summary["late_ms_max"] >= 300, summary


def test_missing_bag_exits_nonzero_with_a_clear_message(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "lidar_quality_ros.bag_player", str(tmp_path / "nope")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert f"bag not found: {tmp_path / 'nope'}" in proc.stdout + proc.stderr


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_installed_executable_loops_until_signal(ros, tmp_path, signame):
    make_bag(tmp_path / "b", frames=3)
    col = ros.collector(PointCloud2, "/pts")
    proc = ros.spawn([str(executable("lidar_quality_ros", "bag_player")), str(tmp_path / "b"), "--loop",
                      "--topics", "/pts", "--wait-for-subscribers", "1"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert col.wait_for(5, timeout=30.0), "no message from the installed bag_player"
    proc.send_signal(getattr(signal, signame))
    out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "played" in out


# --------------------------------------------------------------------------- any bag
def packets_and_clouds_bag(path, packets):
    """An sqlite3 bag as older recorders left it (metadata v5, empty storage identifier and
    serialization format, in the .db3 too) with a driver's packet topic (``packets``: (type,
    raw bytes) per message; no rclpy class here) beside /pts clouds."""
    sent = []
    with BagWriter(path, storage="sqlite3") as w:
        for i, (msgtype, raw) in enumerate(packets):
            log = T0 + i * PERIOD
            w.write("/driver/packets", msgtype, log, raw)
            h = Header(frame_id="lidar")
            h.stamp.sec, h.stamp.nanosec = divmod(log, 10**9)
            cloud = create_xyz_cloud(h, np.full((10, 3), i, np.float32))
            w.write("/pts", "sensor_msgs/msg/PointCloud2", log + 1, cloud)
            sent.append(cloud)
    humble_metadata(path, db_format="")
    return sent


def test_unknown_types_are_skipped_with_one_warning_and_the_rest_played(ros, tmp_path, capfd):
    name = min(REAL_BAGS)
    try:       # the real packets where they are, else bytes of our own under a driver's type
        from lidar_quality_ros.bag_io import read_bag
        packets = [(m.msgtype, m.raw) for m in read_bag(real_bag(name))][:2] * 2
    except pytest.skip.Exception:
        packets = [("velodyne_msgs/msg/VelodyneScan", bytes([0, 1, 0, 0]) + bytes(64))] * 4
    sent = packets_and_clouds_bag(tmp_path / "b", packets)
    col = ros.collector(PointCloud2, "/pts", qos_profile_sensor_data)  # as recorded
    player = play(ros, tmp_path / "b")
    assert col.wait_for(len(sent), timeout=10.0) and col.messages == sent
    msgtype = packets[0][0]
    assert player.summary()["skipped_types"] == {msgtype: ["/driver/packets"]}
    assert list(player.summary()["topics"]) == ["/pts"]
    err = capfd.readouterr().err
    assert err.count(msgtype) == 1 and "not played" in err


@pytest.mark.parametrize("name", sorted(REAL_BAGS))
def test_real_recordings_without_a_traceback(ros, tmp_path, name):
    """A raw-packet recording alone: nothing is playable here; said once, clearly (exit 2,
    a node that cannot start), never a traceback."""
    bag = real_bag(name)
    topic, msgtype, _, _ = REAL_BAGS[name]
    proc = subprocess.run([sys.executable, "-m", "lidar_quality_ros.bag_player", str(bag)],
                          capture_output=True, text=True, timeout=60)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out
    assert "Traceback" not in out
    assert out.count(f"message type {msgtype} (topic {topic}) is not available here") == 1
    assert "nothing to play" in out and f"{topic}: {msgtype}" in out
