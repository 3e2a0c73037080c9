"""process_bag: the annotated bag (inputs copied, one output per node and frame, LMD ids /
order / values as LmdProcessor gives them), corrupted frames dropped and counted, CLI
errors, parameter overrides, the installed executable. Real bags: a 3-frame simulated
perception bag run through the reference perception (``perception_bags``)."""
import json
import subprocess

import numpy as np
import pytest
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_ros.bag_io import BagWriter, bag_info, read_bag
from lidar_quality_ros.perception_bag import DEFAULT_TOPICS, HEAD_TOPIC, perception_frames
from lidar_quality_ros.qos import SENSOR_QOS
from lidar_quality_tools.process import OUTPUTS, Drop, Runner, _run, main, process_bag
from lmd_ros.pipeline import LmdProcessor, LmdSettings, default_model_paths
from tf_scenes import detections_in_frame
from node_shell_checks import executable
from perception_bags import simulated_perception_bags
from realbags import REAL_BAGS, real_bag
from rclpy.serialization import deserialize_message, serialize_message
from reference_perception.cli import Perception
from sensor_msgs.msg import PointCloud2

N_FRAMES = 3
OUT_TOPICS = [t for outs in OUTPUTS.values() for t, _ in outs]
TOPICS = {**{k: t for k, t in DEFAULT_TOPICS.items() if k not in ("points_gt", "gt_objects")},
          **{f"head_{k}{v}": HEAD_TOPIC.format(k=k) + v for k in range(2)
             for v in ("", "/variance")}}


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return simulated_perception_bags(tmp_path_factory.mktemp("process"), Perception(heads=2),
                                     n_sequences=1, n_frames=N_FRAMES, seed=3, columns=512)


@pytest.fixture(scope="module")
def bag(bags):
    return bags / "seq_00"


def messages(path, topics=None):
    return [(m.topic, m.msgtype, m.stamp_ns, m.raw) for m in read_bag(path, topics)]


def decoded(path, topic):
    return [m.decode() for m in read_bag(path, {topic})]


def ids(det_array):
    return [d.id for d in det_array.detections]


def test_annotated_bag(bag, tmp_path):
    out = tmp_path / "out"
    summary = process_bag(bag, out, progress=False)
    assert json.loads(json.dumps(summary)) == summary
    for node in ("lmd", "lms", "mimo"):
        s = summary["nodes"][node]
        assert (s["frames_in"], s["frames_out"], s["frames_dropped"]) == (N_FRAMES,) * 2 + (0,)
        assert s["wall_s"] > 0 and s["frames_per_s"] > 0
    inputs = messages(bag)
    assert messages(out, {t for t, *_ in inputs}) == inputs      # every input, unchanged
    info = bag_info(out)
    assert {t: info.topics[t].count for t in OUT_TOPICS} == dict.fromkeys(OUT_TOPICS, N_FRAMES)
    clouds = list(read_bag(bag, {"/lidar/points"}))
    for topic in OUT_TOPICS:    # log time and header stamp of the frame's cloud
        outs = list(read_bag(out, {topic}))
        assert [m.stamp_ns for m in outs] == [c.stamp_ns for c in clouds]
        assert [m.decode().header for m in outs] == [c.decode().header for c in clouds]
    times = [m.stamp_ns for m in read_bag(out)]
    assert times == sorted(times)

    settings = LmdSettings()    # the installed lmd_node.yaml's settings
    proc = LmdProcessor(settings, MetaModels(*default_model_paths("threshold"),
                                             settings.feature_names()))
    frames = list(perception_frames(bag, want=("points", "detections", "proposals",
                                               "segmentation"), heads=2))
    lmd_dets = decoded(out, "/lmd/output/detections")
    lmd_quality = decoded(out, "/lmd/output/quality")
    lms_points = decoded(out, "/lms/output/points")
    mimo_dets = decoded(out, "/mimo/output/detections")
    assert summary["nodes"]["lmd"]["counts"]["detections.in"] == sum(
        len(f.detections.detections) for f in frames)
    for f, dets, quality, points, merged in zip(frames, lmd_dets, lmd_quality, lms_points,
                                                mimo_dets):
        in_ids = ids(f.detections)
        assert len(in_ids) > 0
        assert ids(dets) == in_ids
        assert [q.detection_id for q in quality.detections] == in_ids
        assert [q.detection_index for q in quality.detections] == list(range(len(in_ids)))
        direct = proc.process(f.points, f.detections, f.proposals)
        np.testing.assert_allclose([q.confidence for q in quality.detections],
                                   direct.confidence, rtol=1e-9)
        np.testing.assert_allclose([q.predicted_iou for q in quality.detections],
                                   direct.predicted_iou, rtol=1e-9)
        assert points.width * points.height == f.segmentation.width * f.segmentation.height
        assert "confidence" in [pf.name for pf in points.fields]
        assert 0 < len(merged.detections) <= sum(len(h.detections) for h in f.heads)


def corrupted_copy(bag, dst):
    """``bag`` with frame 0's proposals and head_0 truncated bytes, frame 1's cloud and
    frame 2's segmentation clouds with a truncated data buffer; the cloud topic recorded
    with sensor-data QoS."""
    stamps = sorted({m.stamp_ns for m in read_bag(bag, {"/lidar/points"})})
    with BagWriter(dst) as w:
        for m in read_bag(bag):
            raw = m.raw
            frame = stamps.index(m.stamp_ns) if m.stamp_ns in stamps else -1
            if (m.topic, frame) in (("/perception/proposals", 0), ("/perception/head_0", 0)):
                raw = raw[:len(raw) // 2]
            if (m.topic, frame) in (("/lidar/points", 1), ("/perception/segmentation", 2)):
                msg = deserialize_message(raw, PointCloud2)
                msg.data = bytes(msg.data)[:len(msg.data) - 7]
                raw = serialize_message(msg)
            w.write(m.topic, m.msgtype, m.stamp_ns, raw,
                    qos=[SENSOR_QOS] if m.topic == "/lidar/points" else ())


def test_bad_frames_are_dropped_and_counted(bag, tmp_path, capsys):
    src, out = tmp_path / "bad", tmp_path / "out"
    corrupted_copy(bag, src)
    summary = process_bag(src, out, progress=False)
    nodes = summary["nodes"]
    assert nodes["lmd"]["frames_out"] == 1
    assert nodes["lmd"]["dropped"] == {"undecodable_input": 1, "malformed_cloud": 1}
    assert nodes["lms"]["frames_out"] == 2 and nodes["lms"]["dropped"] == {"malformed_cloud": 1}
    # MIMO, as the node: an undecodable head is left out, the frame merged from the other
    assert nodes["mimo"]["frames_out"] == 3 and nodes["mimo"]["issues"]["undecodable"] == 1
    assert all(n["frames_in"] == N_FRAMES for n in nodes.values())
    info = bag_info(out)
    assert [info.topics[t].count for t in OUT_TOPICS] == [1, 1, 2, 2, 3, 3]
    assert messages(out, set(bag_info(src).topics)) == messages(src)   # copied unchanged
    assert info.topics["/lidar/points"].qos == [SENSOR_QOS]
    # the processed LMD frame is frame 2, with every detection in order
    frames = list(perception_frames(src, want=("detections",), require="detections"))
    assert ids(decoded(out, "/lmd/output/detections")[0]) == ids(frames[2].detections)
    err = capsys.readouterr().err
    assert err.count("dropped") == 3 and "CloudFormatError" in err


def renamed_copy(bag, dst, rename):
    """``bag`` with topics renamed (``rename``: old -> new), messages unchanged."""
    with BagWriter(dst) as w:
        for m in read_bag(bag):
            w.write(rename.get(m.topic, m.topic), m.msgtype, m.stamp_ns, m.raw)


def test_node_without_output_fails_naming_the_reason(bag, tmp_path, capsys):
    """Topics under other names: LMD gets no proposals (every frame dropped), MIMO none of
    its topics; both named with the reason and exit 1, LMS's output still written."""
    src, out = tmp_path / "renamed", tmp_path / "out"
    renamed_copy(bag, src, {"/perception/proposals": "/detector/proposals",
                            **{f"/perception/head_{k}{v}": f"/detector/head_{k}{v}"
                               for k in range(2) for v in ("", "/variance")}})
    assert main(["--bag", str(src), "--out", str(out), "--no-progress"]) == 1
    cap = capsys.readouterr()
    assert "lms" in cap.out
    failed = [line for line in cap.err.splitlines() if line.startswith("process_bag: FAILED")]
    assert len(failed) == 2, cap.err
    lmd, mimo = failed
    assert "lmd processed no frame" in lmd and "input topics not in the bag: " \
        "/perception/proposals" in lmd and f"missing_input {N_FRAMES}" in lmd
    assert "/detector/proposals" in lmd                       # what the bag has instead
    assert "mimo processed no frame" in mimo and "its input topics are not in the bag" in mimo
    assert "/perception/head_1/variance" in mimo and "exit 1" in cap.err
    assert bag_info(out).topics["/lms/output/segments"].count == N_FRAMES


def test_every_frame_malformed_fails_with_the_reasons_counted(bag, tmp_path):
    src, out = tmp_path / "bad", tmp_path / "out"
    with BagWriter(src) as w:
        for m in read_bag(bag):
            raw = m.raw
            if m.topic == "/lidar/points":
                msg = deserialize_message(raw, PointCloud2)
                msg.data = bytes(msg.data)[:len(msg.data) - 7]
                raw = serialize_message(msg)
            w.write(m.topic, m.msgtype, m.stamp_ns, raw)
    summary = process_bag(src, out, progress=False)
    assert summary["no_output"] == {
        "lmd": f"every frame dropped ({N_FRAMES}): malformed_cloud {N_FRAMES}"}
    assert summary["nodes"]["lmd"]["frames_in"] == N_FRAMES
    assert summary["nodes"]["mimo"]["frames_out"] == N_FRAMES       # no points needed
    assert main(["--bag", str(src), "--out", str(tmp_path / "cli"), "--no-progress",
                 "--nodes", "mimo"]) == 0


@pytest.mark.parametrize("args, message", [
    (["--bag", "{tmp}/nope"], "no such file"),
    (["--nodes", "lmd,foo"], "unknown node"),
    (["--param", "lmd.no_such=1"], "unknown parameter lmd.no_such"),
    (["--param", "lmd.proposal_mode=bogus"], "proposal_mode"),
    (["--param", "lmd.iou_threshold=high"], "expected a float"),
    (["--param", "mimo.eps"], "expected <node>.<name>=<value>"),
    # ranges and choices as the node declares them (before: accepted, failing later or not)
    (["--param", "mimo.eps=1.0"], "'eps' = 1.0: outside (0, 1)"),
    (["--param", "mimo.num_heads=17"], "'num_heads' = 17: outside [1, 16]"),
    (["--param", "lmd.min_confidence=2.0"], "'min_confidence' = 2.0: outside [0, 1]"),
    (["--param", "mimo.output_scores=best"], "expected one of ['confidence', 'merged']"),
    (["--param", "lms.width=512", "--nodes", "lmd"], "not in --nodes"),
    (["--out", "{bag}", "--overwrite"], "overlaps"),
])
def test_cli_argument_errors(bag, tmp_path, capsys, args, message):
    argv = ["--bag", str(bag), "--out", str(tmp_path / "out"), "--no-progress"]
    argv += [a.format(tmp=tmp_path, bag=bag) for a in args]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("node", ["lmd", "lms", "mimo"])
def test_parameters_are_the_node_declarations_and_the_yaml_passes_them(ros, node):
    """One declaration per parameter: the node declares exactly process_bag's specs (same
    default, description, range, choices, read-only status), and the shipped config YAML
    names only declared parameters with values they accept."""
    import importlib

    from lidar_quality_ros.params import config_parameters
    from lidar_quality_tools.process import NODES, node_config, node_parameters, node_specs

    pkg = NODES[node]
    cls = {"lmd": "LmdNode", "lms": "LmsNode", "mimo": "MimoNode"}[node]
    n = ros.start(getattr(importlib.import_module(f"{pkg}.{node}_node"), cls))
    specs = node_specs(node)
    declared = [k for k in n._parameters if k not in ("use_sim_time",
                                                      "start_type_description_service")]
    assert sorted(declared) == sorted(specs)
    for name, spec in specs.items():
        d = n.describe_parameter(name)
        assert n.get_parameter(name).value == spec.default, name
        assert d.description.startswith(spec.description), name
        assert d.read_only == (not spec.live), name
    config = config_parameters(pkg, f"{node}_node")
    assert set(config) <= set(specs)
    for name, value in config.items():
        specs[name].check(value)
    node_config(node, node_parameters(node))       # the YAML's settings validate


def test_existing_output_needs_overwrite(bag, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["--bag", str(bag), "--out", str(out), "--nodes", "mimo", "--no-progress"]
    assert main(argv) == 0
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and "--overwrite" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0
    assert set(bag_info(out).topics) >= {"/mimo/output/detections"}
    assert "/lmd/output/quality" not in bag_info(out).topics


def test_param_override_and_folder_of_bags(bags, tmp_path, capsys):
    """``--bag <folder>`` writes OUT/<bag name>; proposal_mode=none selects the none-mode
    models and still scores every detection."""
    out = tmp_path / "out"
    assert main(["--bag", str(bags), "--out", str(out), "--nodes", "lmd", "--no-progress",
                 "--param", "lmd.proposal_mode=none"]) == 0
    assert "lmd" in capsys.readouterr().out
    res = out / "seq_00"
    none_models = MetaModels(*default_model_paths("none"),
                             LmdSettings(proposal_mode="none").feature_names())
    quality = decoded(res, "/lmd/output/quality")
    assert len(quality) == N_FRAMES
    assert {(q.confidence_model_id, q.iou_model_id) for q in quality} == {
        (none_models.confidence_model_id, none_models.iou_model_id)}
    inputs = decoded(bags / "seq_00", "/perception/detections")
    assert [ids(d) for d in decoded(res, "/lmd/output/detections")] == [ids(d) for d in inputs]
    assert all(np.isfinite(q.confidence) for a in quality for q in a.detections)


def test_installed_executable(bag, tmp_path):
    out = tmp_path / "out"
    ok = subprocess.run([str(executable("lidar_quality_tools", "process_bag")), "--bag",
                         str(bag), "--out", str(out), "--nodes", "lms,mimo", "--no-progress"],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "lms" in ok.stdout and "mimo" in ok.stdout and "frames/s" in ok.stdout
    bad = subprocess.run([str(executable("lidar_quality_tools", "process_bag")), "--bag",
                          str(bag), "--out", str(out)], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "exists" in bad.stderr


# --------------------------------------------------------------------------- any bag
@pytest.mark.parametrize("name", sorted(REAL_BAGS))
def test_real_recordings_copied_through_with_the_no_frame_outcome(name, tmp_path, capsys):
    """A driver's raw-packet recording (older metadata, a type unknown here): no traceback;
    the packets are copied to the output unchanged, the type reported once, and every node
    ends with "its input topics are not in the bag" (exit 1, as documented)."""
    bag = real_bag(name)
    topic, msgtype, count, _ = REAL_BAGS[name]
    out = tmp_path / "out"
    assert main(["--bag", str(bag), "--out", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.count(f"message type {msgtype}") == 1 and topic in err
    for node in ("lmd", "lms", "mimo"):
        assert f"FAILED: {node} processed no frame of {bag}: its input topics are not in " \
               "the bag" in err
    assert messages(out) == messages(bag)           # the packets, byte for byte
    assert bag_info(out).topics[topic].msgtype == msgtype
    summary = process_bag(bag, tmp_path / "again", nodes="mimo", progress=False)
    assert summary["unknown_types"] == {msgtype: [topic]}
    assert summary["messages_copied"] == count and summary["frames"] == 0


AUTOWARE = {"points": "/sensing/lidar/top/pointcloud",
            "detections": "/perception/object_recognition/detection/objects",
            "proposals": "/perception/object_recognition/detection/proposals",
            "segmentation": "/perception/segmentation/pointcloud",
            **{f"head_{k}{v}": f"/ensemble/member_{k}{v}" for k in range(2)
               for v in ("", "/variance")}}


def test_topic_options_give_the_outputs_of_the_default_names(bag, tmp_path, capsys):
    """Every input under a user's own names, named with --topic: the same outputs."""
    src = tmp_path / "autoware"
    renamed_copy(bag, src, {t: AUTOWARE[k] for k, t in TOPICS.items()})
    assert main(["--bag", str(bag), "--out", str(tmp_path / "ref"), "--no-progress"]) == 0
    argv = ["--bag", str(src), "--out", str(tmp_path / "out"), "--no-progress"]
    assert main(argv + [a for k, t in AUTOWARE.items() for a in ("--topic", f"{k}={t}")]) == 0
    for t in OUT_TOPICS:   # decoded: CDR alignment padding is not always zeroed
        out, ref = decoded(tmp_path / "out", t), decoded(tmp_path / "ref", t)
        assert len(out) == len(ref) == N_FRAMES
        assert all(a == b or repr(a) == repr(b) for a, b in zip(out, ref)), t   # NaN too
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["--bag", str(src), "--out", str(tmp_path / "x"), "--topic", "cloud=/a"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "unknown topic key 'cloud'" in err
    assert "points, points_gt, gt_objects, detections, proposals, segmentation, head_<k>, " \
           "head_<k>/variance" in err
    with pytest.raises(SystemExit) as e:
        main(["--bag", str(src), "--out", str(tmp_path / "x"), "--topic", "points"])
    assert e.value.code == 2 and "expected KEY=/topic/name" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def _failing_runner(after: int):
    """An LMD runner interrupted (Ctrl-C) at its frame ``after``."""
    seen = []

    def run(get):
        seen.append(get("points"))
        if len(seen) > after:
            raise KeyboardInterrupt
        raise Drop("missing_input")

    return Runner("lmd", {"points": "/lidar/points"}, ("points",), run)


def test_failed_run_leaves_no_output_and_needs_no_overwrite(bag, tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        _run(bag, out, [_failing_runner(after=1)], progress=False)
    assert list(tmp_path.iterdir()) == []          # nothing at the target nor beside it
    argv = ["--bag", str(bag), "--out", str(out), "--nodes", "mimo", "--no-progress"]
    assert main(argv) == 0                          # no --overwrite: there was nothing
    done = messages(out)
    with pytest.raises(KeyboardInterrupt):          # a failed replacement keeps it
        _run(bag, out, [_failing_runner(after=2)], progress=False)
    assert messages(out) == done and list(tmp_path.iterdir()) == [out]
    # several bags: OUT/<name> each, OUT itself may exist (a failed run's folder)
    (tmp_path / "many").mkdir()
    assert main(["--bag", str(bag.parent), "--out", str(tmp_path / "many"), "--nodes", "mimo",
                 "--no-progress"]) == 0
    assert [m[:3] for m in messages(tmp_path / "many" / bag.name)] == [m[:3] for m in done]
    capsys.readouterr()


def test_detections_in_another_frame_with_tf_static(tmp_path):
    """Issue 16 (frames): detections / proposals in base_link and /tf_static base_link <-
    lidar_top in the bag give the outputs of the same scene recorded in one frame; without
    the transform every frame is dropped as no_transform."""

    from geometry_msgs.msg import TransformStamped
    from lidar_quality_core import synthetic
    from lidar_quality_core.transforms import Transform
    from lmd_frames import frame_messages
    from std_msgs.msg import Header
    from tf2_msgs.msg import TFMessage

    t_base_lidar = Transform.from_yaw(0.3, (1.2, 0.1, 1.8))

    def moved(msg):
        return detections_in_frame(msg, t_base_lidar, "base_link")

    def write(path, base_link, tf):
        with BagWriter(path) as w:
            if tf:
                ts = TransformStamped()
                ts.header.frame_id, ts.child_frame_id = "base_link", "lidar_top"
                v, r = ts.transform.translation, ts.transform.rotation
                v.x, v.y, v.z = t_base_lidar.translation.tolist()
                r.x, r.y, r.z, r.w = t_base_lidar.rotation.tolist()
                w.write("/tf_static", "tf2_msgs/msg/TFMessage", 1, TFMessage(transforms=[ts]))
            for k in range(2):
                f = synthetic.synthetic_frame(n_points=10_000, n_objects=8, n_proposals=80,
                                              seed=40 + k)
                cloud, dets, props = frame_messages(f, k + 1)
                for m in (dets, props):  # own headers: moved() changes one frame_id
                    m.header = Header(stamp=cloud.header.stamp, frame_id="lidar_top")
                if base_link:
                    dets, props = moved(dets), moved(props)
                for topic, msg in ((DEFAULT_TOPICS["detections"], dets),
                                   (DEFAULT_TOPICS["proposals"], props)):
                    w.write(topic, "vision_msgs/msg/Detection3DArray", (k + 1) * 10**9, msg)
                w.write(DEFAULT_TOPICS["points"], "sensor_msgs/msg/PointCloud2",
                        (k + 1) * 10**9, cloud)

    runs = {}
    for name, base_link, tf in (("one", False, False), ("base", True, True),
                                ("missing", True, False)):
        write(tmp_path / name, base_link, tf)
        runs[name] = process_bag(tmp_path / name, tmp_path / f"{name}_out", nodes=("lmd",),
                                 progress=False)["nodes"]["lmd"]
    assert runs["missing"]["dropped"] == {"no_transform": 2} and runs["missing"]["frames_out"] == 0
    assert runs["base"]["frames_out"] == 2 and runs["base"]["issues"] == {}
    one, base = (decoded(tmp_path / f"{n}_out", "/lmd/output/quality") for n in ("one", "base"))
    assert [q.header.frame_id for q in base] == ["base_link"] * 2
    for a, b in zip(one, base):
        np.testing.assert_allclose([e.confidence for e in b.detections],
                                   [e.confidence for e in a.detections], rtol=0, atol=1e-9)
        np.testing.assert_allclose([e.predicted_iou for e in b.detections],
                                   [e.predicted_iou for e in a.detections], rtol=0, atol=1e-9)


def test_each_bag_of_a_batch_is_a_stream_of_its_own(bag, tmp_path):
    """Two copies of a bag in one run give byte-identical outputs: the second does not
    inherit the first one's drift window (nor intensity decision, beam table)."""
    import shutil

    src = tmp_path / "in"
    for name in ("a", "b"):
        shutil.copytree(bag, src / name)
    out = tmp_path / "out"
    assert main(["--bag", str(src), "--out", str(out), "--no-progress"]) == 0
    first, second = messages(out / "a", OUT_TOPICS), messages(out / "b", OUT_TOPICS)
    assert len(first) == len(second) > 0
    assert first == second
    quality = decoded(out / "b", "/lmd/output/quality")
    assert [q.drift_window_frames for q in quality] == list(range(1, N_FRAMES + 1))
