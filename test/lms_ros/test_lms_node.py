"""lms_node: parameters, sensor QoS inputs, outputs equal to the model store's models on
the pipeline's metrics (float32 / uint8 probabilities, one or two clouds), bad input,
model refusal, real sensor clouds, the installed executable.

The models are real: XGBoost fitted once per session on small simulated scans with noisy
probabilities (``lms_scans.train_models``)."""
import subprocess

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.pcd import read_pcd
from lidar_quality_core.pointcloud import create_cloud, read_fields
from lidar_quality_msgs.msg import SegmentQualityArray
from lms_ros.lms_node import LmsNode
from lms_ros.pipeline import CLASS_NAMES, decode, frame_metrics, probability_field
from lidar_quality_core.lms.segment_metrics import to_points
from lms_scans import (cloud, frame_cloud, frame_probs, header, node_parameters, noisy_probs,
                       scans, settings, train_models)
from node_shell_checks import (assert_declared_with_descriptions, assert_sensor_qos,
                               assert_yaml_matches_declared, diag_values, executable,
                               run_executable_and_signal, wait_until)
from realdata import REAL_FILES, realdata_dir
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

PARAMS = ("classifier_path", "regressor_path", "class_names", "channels", "fov_up_deg",
          "fov_down_deg", "width", "use_ring", "ring_zero_top", "ring_field",
          "min_segment_points", "sum_tolerance", "separate_probabilities", "publish_markers",
          "sensor", "sensors_file", "beam_elevations_deg", "beam_rows", "no_pixel_warn_ratio",
          "no_pixel_error_ratio",
          "sync_mode", "sync_slop", "sync_queue_size", "processing_queue_size",
          "diagnostics_period",
          "diagnostics_window", "drop_warn_fraction", "drop_error_fraction", "input_timeout",
          "input_error_timeout")
OUT_FIELDS = ["x", "y", "z", "label", "segment", "confidence", "predicted_iou"]


@pytest.fixture(scope="session")
def frames():
    return scans(3, 2)


@pytest.fixture(scope="session")
def models_dir(tmp_path_factory, frames):
    """``<dir>/lms/lms_{classifier,regressor}.joblib`` (the layout of models_dir(), so
    that LQ_MODELS_DIR=<dir> makes them the defaults)."""
    root = tmp_path_factory.mktemp("lms_models")
    train_models(root / "lms", frames)
    return root


def params(models_dir, **extra):
    d = models_dir / "lms"
    return node_parameters(**{"classifier_path": str(d / "lms_classifier.joblib"),
                              "regressor_path": str(d / "lms_regressor.joblib"), **extra})


def load_models(models_dir):
    p = params(models_dir)
    return MetaModels(p["classifier_path"], p["regressor_path"], settings().metric_names())


def expected(msg, models, s=None, probabilities=None):
    """(SegmentResult, per-segment conf, per-segment iou, per-point (conf, iou)) computed
    without the node."""
    s = settings() if s is None else s
    res = frame_metrics(decode(msg, s, probabilities), s)
    conf, iou = models.predict(res.features)
    per_point = to_points(res, np.stack([conf, iou], axis=1).astype(np.float32))
    return res, conf, iou, per_point


class Io:
    def __init__(self, ros, node, separate=False, markers=False):
        self.points = ros.sensor_publisher(PointCloud2, "input/points")
        self.probs = ros.sensor_publisher(PointCloud2, "input/probabilities") if separate else None
        self.out = ros.collector(PointCloud2, "output/points")
        self.segments = ros.collector(SegmentQualityArray, "output/segments")
        self.markers = ros.collector(MarkerArray, "output/markers") if markers else None
        assert ros.wait_for_match(self.points)
        assert self.probs is None or ros.wait_for_match(self.probs)
        assert ros.wait_for_match(self.out.subscription)
        assert ros.wait_for_match(self.segments.subscription)
        if markers:
            assert wait_until(lambda: node.pub_markers.get_subscription_count() > 0)

    def send(self, points, probabilities=None):
        if probabilities is not None:
            self.probs.publish(probabilities)
        self.points.publish(points)


def check_output(out, seg_msg, sent, res, conf, iou, per_point):
    """The node's messages equal the expected values for the sent cloud."""
    assert out.header == sent.header and seg_msg.header == sent.header
    assert [f.name for f in out.fields] == OUT_FIELDS
    assert out.width * out.height == len(res.point_segment)
    xyz = read_fields(sent, ["x", "y", "z"])
    np.testing.assert_array_equal(read_fields(out, ["x", "y", "z"]), xyz)
    np.testing.assert_array_equal(read_fields(out, ["segment"], np.int64)[:, 0],
                                  res.point_segment)
    np.testing.assert_array_equal(read_fields(out, ["label"], np.int64)[:, 0], res.point_class)
    np.testing.assert_array_equal(read_fields(out, ["confidence", "predicted_iou"]), per_point)
    kid = res.kept_ids
    assert len(seg_msg.segments) == res.n_segments
    got_c = np.array([q.confidence for q in seg_msg.segments])
    got_u = np.array([q.predicted_iou for q in seg_msg.segments])
    np.testing.assert_array_equal(got_c[kid], conf)
    np.testing.assert_array_equal(got_u[kid], iou)
    assert np.isnan(np.delete(got_c, kid)).all()
    assert [q.segment_id for q in seg_msg.segments] == list(range(res.n_segments))
    assert [q.class_index for q in seg_msg.segments] == res.segment_class.tolist()
    assert [q.projected_point_count for q in seg_msg.segments] == res.size_projected.tolist()


# ---------------------------------------------------------------- parameters, QoS
def test_parameters_and_qos(ros, models_dir):
    node = ros.start(LmsNode, parameters=params(models_dir))
    assert_declared_with_descriptions(node, set(PARAMS))
    assert_yaml_matches_declared(node, "lms_ros")
    assert node.inputs.topics == ["input/points"]
    assert_sensor_qos(node, "input/points")


def test_separate_probabilities_subscribes_two_inputs(ros, models_dir):
    node = ros.start(LmsNode, parameters=params(models_dir, separate_probabilities=True))
    assert node.inputs.topics == ["input/points", "input/probabilities"]
    for topic in node.inputs.topics:
        assert_sensor_qos(node, topic)


@pytest.mark.parametrize("bad, match", [
    ({"channels": 0}, "channels"),
    ({"fov_up_deg": -30.0}, "fov"),
    ({"class_names": ["car", "car"]}, "duplicate"),
    ({"class_names": ["road", "intensity"]}, "clash"),
    ({"min_segment_points": 0}, "min_segment_points"),
    ({"sum_tolerance": 1.5}, "sum_tolerance"),
    ({"sync_mode": "fuzzy"}, "sync_mode"),
])
def test_invalid_parameters_refused(ros, models_dir, bad, match):
    with pytest.raises(Exception, match=match):
        ros.start(LmsNode, parameters={**params(models_dir), **bad})


# ---------------------------------------------------------------- model refusal
def test_missing_model_refuses_to_start(ros, models_dir, tmp_path):
    p = params(models_dir, regressor_path=str(tmp_path / "nope.joblib"))
    with pytest.raises(RuntimeError, match=r"cannot load the LMS meta models .*nope\.joblib: "
                                           r"missing manifest"):
        ros.start(LmsNode, parameters=p)


def test_class_count_mismatch_refuses_to_start(ros, models_dir):
    p = params(models_dir, class_names=list(CLASS_NAMES[:-1]))  # 13 classes, models for 14
    with pytest.raises(RuntimeError, match=r"for 13 classes \(112 metrics\).*feature schema "
                                           r"mismatch.*class_names") as e:
        ros.start(LmsNode, parameters=p)
    assert "N_cyclist" in str(e.value)


def test_executable_without_models_exits_with_reason(ros, tmp_path):
    proc = ros.spawn([str(executable("lms_ros", "lms_node"))], stdout=subprocess.PIPE,
                     stderr=subprocess.STDOUT, text=True,
                     extra_env={"LQ_MODELS_DIR": str(tmp_path)})
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode != 0, out
    assert "lms_classifier.joblib" in out and "missing manifest" in out, out


# ---------------------------------------------------------------- outputs
def test_outputs_equal_models_on_frame_metrics(ros, models_dir, frames):
    node = ros.start(LmsNode, parameters=params(models_dir))
    io = Io(ros, node, markers=True)
    models = load_models(models_dir)
    f = frames[1]
    p = frame_probs(f, 77)
    sent = [frame_cloud(f, p, sec=1), frame_cloud(f, p, sec=2, quantize=True)]
    for k, msg in enumerate(sent, start=1):
        io.send(msg)
        assert io.out.wait_for(k, timeout=15.0) and io.segments.wait_for(k, timeout=5.0)
    assert io.markers.wait_for(2, timeout=5.0)
    conf_all = []
    for k, msg in enumerate(sent):
        res, conf, iou, per_point = expected(msg, models)
        check_output(io.out.messages[k], io.segments.messages[k], msg, res, conf, iou, per_point)
        assert len(io.markers.messages[k].markers[-1].points) == len(res.kept_ids)
        conf_all.append(conf)
        sq = io.segments.messages[k]   # models without a profile: the monitor is off
        assert (sq.version, sq.drift_level) == (sq.MESSAGE_VERSION, sq.DRIFT_OFF)
        assert np.isnan(sq.drift_score) and not sq.passthrough
    # float32 and uint8: the same labels up to quantization (argmax flips of near ties)
    l32, l8 = (read_fields(m, ["label"], np.int64)[:, 0] for m in io.out.messages)
    assert (l32 == l8).mean() > 0.995
    conf_all = np.concatenate(conf_all)
    assert conf_all.min() < 0.5 < conf_all.max()                 # not a constant model
    status = node.diag.status()
    v = diag_values(status)
    assert status.level == DiagnosticStatus.OK, status.message
    assert v["frames_out"] == "2" and v["points.in"] == str(2 * len(f.xyz))
    assert v["segments.scored"] == str(len(conf_all))
    assert v["model.confidence"] == models.confidence_model_id


def test_two_cloud_mode(ros, models_dir, frames):
    node = ros.start(LmsNode, parameters=params(models_dir, separate_probabilities=True))
    io = Io(ros, node, separate=True)
    models = load_models(models_dir)
    f = frames[0]
    p = frame_probs(f, 5)
    points = cloud(f.xyz, intensity=f.intensity, ring=f.ring, sec=3)
    probs = cloud(f.xyz, p, sec=3, quantize=True)
    # unequal point counts: dropped and counted
    io.send(cloud(f.xyz, intensity=f.intensity, ring=f.ring, sec=2),
            cloud(f.xyz[:-5], p[:-5], sec=2))
    assert wait_until(lambda: node.diag.dropped == 1)
    assert "input/probabilities has" in node.diag.status().message
    io.send(points, probs)
    assert io.out.wait_for(1, timeout=15.0) and io.segments.wait_for(1, timeout=5.0)
    res, conf, iou, per_point = expected(points, models, probabilities=probs)
    check_output(io.out.messages[0], io.segments.messages[0], points, res, conf, iou, per_point)
    status = node.diag.status()  # the dropped frame shows in the lost fraction of the window
    assert status.level == DiagnosticStatus.WARN and "1 of 2 frames lost" in status.message


def test_bad_input_does_not_kill_the_node(ros, models_dir, frames):
    node = ros.start(LmsNode, parameters=params(models_dir, diagnostics_period=0.2,
                                                diagnostics_window=1.0))
    io = Io(ros, node)
    models = load_models(models_dir)
    f = frames[0]
    p = frame_probs(f, 9)

    # 1. truncated data and a missing probability field: dropped, counted, named
    bad = frame_cloud(f, p, sec=1)
    bad.data = bad.data[:1000]
    io.send(bad)
    names = [c for c in CLASS_NAMES if c != "pedestrian"]
    io.send(frame_cloud(f, np.delete(p, CLASS_NAMES.index("pedestrian"), axis=1), sec=2,
                        names=names))
    assert wait_until(lambda: node.diag.dropped == 2)
    status = node.diag.status()
    assert status.level == DiagnosticStatus.WARN and "pedestrian" in status.message
    assert diag_values(status)["dropped.malformed_cloud"] == "2"

    # 2. NaN points, unusable and unnormalized probabilities: processed, flagged
    xyz = f.xyz.astype(np.float32).copy()
    xyz[:50] = np.nan
    q = p.copy()
    q[100:300] *= 3.0
    q[400] = np.nan
    msg = cloud(xyz, q, intensity=f.intensity, ring=f.ring, sec=3)
    io.send(msg)
    assert io.out.wait_for(1, timeout=15.0) and io.segments.wait_for(1, timeout=5.0)
    res, conf, iou, per_point = expected(msg, models)
    out = io.out.messages[0]
    assert out.width == len(xyz)
    np.testing.assert_array_equal(read_fields(out, ["segment"], np.int64)[:, 0], res.point_segment)
    np.testing.assert_array_equal(read_fields(out, ["confidence", "predicted_iou"]), per_point)
    assert (res.point_segment[:50] == -1).all() and np.isnan(per_point[:50]).all()
    assert np.isnan(per_point[400]).all()
    msg_text = node.diag.status().message
    assert "200 of" in msg_text and "renormalized" in msg_text and "unusable" in msg_text

    # 3. an empty cloud: an empty output, not an error
    io.send(cloud(np.zeros((0, 3)), np.zeros((0, len(CLASS_NAMES)), np.float32), sec=4))
    assert io.out.wait_for(2, timeout=15.0) and io.segments.wait_for(2, timeout=5.0)
    assert io.out.messages[1].width == 0 and io.segments.messages[1].segments == []

    # 4. a valid frame afterwards is processed; the warnings clear after two publications
    # (hold) and the drops leave the diagnostics window
    ok = frame_cloud(f, p, sec=5)
    io.send(ok)
    assert io.out.wait_for(3, timeout=15.0) and io.segments.wait_for(3, timeout=5.0)
    check_output(io.out.messages[2], io.segments.messages[2], ok, *expected(ok, models))
    assert wait_until(lambda: node.diag.status().level == DiagnosticStatus.OK, timeout=10.0), \
        node.diag.status().message
    status = node.diag.status()
    v = diag_values(status)
    assert v["warnings.cloud"] == "2"
    assert node.diag.dropped == 2 and v["frames_out"] == "3"
    assert v["points.invalid"] == "51" and v["points.renormalized"] == "200"
    assert "dropped.processing_error" not in v


# ---------------------------------------------------------------- real sensor clouds
# channels of each sensor; the ring field: VLP-16 has nebula's "channel" (0 = lowest beam),
# for XT16 / XT32 (uniform beams) we number the beams top-down (Hesai: channel 1 = top);
# the others go without a ring (rows from elevation bins of their vertical field of view)
REAL = {"hesai_40p": 40, "hesai_64": 64, "hesai_at128": 128, "hesai_ot128": 128,
        "hesai_qt128": 128, "hesai_qt64": 64, "hesai_xt16": 16, "hesai_xt32": 32,
        "hesai_xt32m": 32, "velodyne_vlp16": 16, "velodyne_vlp32": 32, "velodyne_vls128": 128}
TOP_DOWN = {"hesai_xt16": (15.0, 2.0), "hesai_xt32": (15.0, 1.0)}  # top beam, spacing [deg]


@pytest.fixture(scope="module")
def realdata():
    d = realdata_dir()
    if not all((d / f"{n}.pcd").is_file() for n in REAL_FILES):
        pytest.skip(f"real sensor clouds not found in {d} (set LQ_REALDATA)")
    return d


def real_cloud(path, stem):
    """(points cloud with synthetic probabilities, node parameters) of a real cloud:
    classes from a height / range rule, probabilities noisy around them."""
    a = read_pcd(path)[0].reshape(-1)
    xyz = np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float32)
    r = np.linalg.norm(xyz, axis=1)
    el = np.degrees(np.arcsin(xyz[:, 2] / np.maximum(r, 1e-6)))
    ground = np.percentile(xyz[:, 2], 5)
    labels = np.where(xyz[:, 2] < ground + 0.3, 1,                      # road
                      np.where(r > 8, 4, np.where(xyz[:, 2] < ground + 1.8, 10, 6)))
    p = dict(channels=REAL[stem], fov_up_deg=float(el.max()) + 0.5,
             fov_down_deg=float(el.min()) - 0.5, width=1024)
    cols = {"intensity": a["intensity"]} if "intensity" in a.dtype.names else {}
    if "channel" in a.dtype.names:
        ring = a["channel"].astype(np.int64)
        cols["channel"] = a["channel"]
        p.update(ring_field="channel", ring_zero_top=False)
    elif stem in TOP_DOWN:
        top, step = TOP_DOWN[stem]
        ring = np.rint((top - el) / step).astype(np.int64)
        cols["ring"] = ring.astype(np.uint16)
        p.update(ring_zero_top=True)
    else:
        ring = np.clip((p["fov_up_deg"] - el) / (p["fov_up_deg"] - p["fov_down_deg"])
                       * REAL[stem], 0, REAL[stem] - 1).astype(np.int64)
    probs = noisy_probs(xyz, ring, labels, seed=len(xyz), cols=1024)
    for k, c in enumerate(CLASS_NAMES):
        cols[probability_field(c)] = probs[:, k]
    msg = create_cloud(header(7), {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **cols})
    return msg, p


@pytest.mark.parametrize("stem", REAL_FILES)
def test_real_sensor_clouds(ros, models_dir, realdata, stem):
    msg, geometry = real_cloud(realdata / f"{stem}.pcd", stem)
    node = ros.start(LmsNode, parameters={**params(models_dir), **geometry,
                                          "ring_zero_top": geometry.get("ring_zero_top", False)})
    io = Io(ros, node)
    io.send(msg)
    assert io.out.wait_for(1, timeout=30.0) and io.segments.wait_for(1, timeout=5.0)
    s = node.settings
    res, conf, iou, per_point = expected(msg, load_models(models_dir), s)
    check_output(io.out.messages[0], io.segments.messages[0], msg, res, conf, iou, per_point)
    n = msg.width
    assert io.out.messages[0].width == n and 10_000 <= n <= 210_000
    # real geometry: most points fall in the image and in a scored segment
    assert res.projection.valid.mean() > 0.95, res.projection.valid.mean()
    assert np.isfinite(per_point[:, 0]).mean() > 0.5
    if stem in TOP_DOWN or stem == "velodyne_vlp16":
        # the ring layout is read right: image rows go down the beams
        xyz = read_fields(msg, ["x", "y", "z"])
        el = np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))
        rows = res.projection.row
        med = [np.median(el[rows == r]) for r in np.unique(rows[rows >= 0])]
        assert len(med) >= s.channels - 1 and (np.diff(med) < 0).all()
    assert node.diag.dropped == 0
    if "intensity" not in [f.name for f in msg.fields]:
        assert "no intensity field" in node.diag.status().message


# ---------------------------------------------------------------- executable
def test_executable_starts_and_stops_cleanly(ros, models_dir, monkeypatch):
    monkeypatch.setenv("LQ_MODELS_DIR", str(models_dir))  # default model paths
    run_executable_and_signal(ros, "lms_ros", "lms_node", ["input/points"], "SIGINT")


def test_launch_file():
    from node_shell_checks import assert_launch_file
    assert_launch_file("lms_ros", "lms_node")
