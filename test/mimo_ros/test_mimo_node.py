"""mimo_node: parameters, merged outputs equal to the pipeline + meta models, stopped heads,
variance and point inputs, malformed heads, model refusal, the installed executable."""
import subprocess

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from lidar_quality_core.iou import iou_3d
from lidar_quality_core.meta_model import MetaModels, fit_estimator, save_pair
from lidar_quality_core.pointcloud import create_xyz_cloud, xyz_intensity
from lidar_quality_core.transforms import Transform
from lidar_quality_ros.tf_listener import tf_static_qos
from tf2_msgs.msg import TFMessage
from lidar_quality_msgs.msg import BoxVarianceArray, ClusterUncertaintyArray
from mimo_ros.mimo_node import MimoNode
from mimo_ros.pipeline import (DEFAULT_CLASS_NAMES, MimoSettings, default_model_paths,
                               frame_features, process_frame)
from tf_scenes import detections_in_frame
from node_shell_checks import (assert_declared_with_descriptions, assert_sensor_qos,
                               assert_yaml_matches_declared, diag_values, executable,
                               run_executable_and_signal, wait_until)
from reference_perception.messages import box_variance_array, detection_array
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

NS_PER_FRAME = 100_000_000  # 10 Hz stamps


def header(i):
    """Frame i: stamp 100 s + i / 10 s."""
    h = Header(frame_id="lidar")
    h.stamp.sec, h.stamp.nanosec = divmod(100_000_000_000 + i * NS_PER_FRAME, 1_000_000_000)
    return h


def make_frame(i, K=2, n_obj=12, n_ghost=3, n_fp=3, n_points=3000):
    """Ground truth cars on a grid; K heads that see each with p = 0.85 with per-object
    noise (so IoUs vary), ghost cars (no ground truth) that every head sees, a few
    single-head false positives; predicted variances; a cloud."""
    rng = np.random.default_rng([i, K])
    gx, gy = np.meshgrid(np.arange(4) * 9.0 + 8.0, np.arange(3) * 7.0 - 7.0)
    gt = np.column_stack([gx.ravel()[:n_obj] + rng.normal(0, 1, n_obj),
                          gy.ravel()[:n_obj] + rng.normal(0, 1, n_obj), np.full(n_obj, -0.9),
                          rng.normal(4.3, 0.2, n_obj), rng.normal(1.8, 0.05, n_obj),
                          rng.normal(1.5, 0.05, n_obj), rng.uniform(-np.pi, np.pi, n_obj)])
    ghosts = np.column_stack([np.arange(n_ghost) * 9.0 + 12.5, np.full(n_ghost, -10.5),
                              np.full(n_ghost, -0.9), np.full((n_ghost, 3), [4.0, 1.8, 1.5]),
                              rng.uniform(-3, 3, n_ghost)])
    objects = np.vstack([gt, ghosts])
    n_all = len(objects)
    sd = rng.uniform(0.02, 0.25, n_all)
    h = header(i)
    heads, variances = [], []
    for k in range(K):
        seen = np.flatnonzero(np.r_[rng.random(n_obj) < 0.85, np.ones(n_ghost, bool)])
        b = objects[seen].copy()
        b[:, :2] += rng.normal(0, 1, (len(seen), 2)) * sd[seen, None]
        b[:, 6] += rng.normal(0, 0.05, len(seen))
        fp = np.column_stack([rng.uniform(5, 40, n_fp), rng.uniform(-12, 12, n_fp),
                              np.full(n_fp, -0.9), np.full(n_fp, 4.0), np.full(n_fp, 1.8),
                              np.full(n_fp, 1.5), rng.uniform(-3, 3, n_fp)])
        boxes = np.vstack([b, fp])
        p_car = np.concatenate([np.where(seen < n_obj, rng.uniform(0.5, 0.95, len(seen)),
                                         rng.uniform(0.3, 0.6, len(seen))),
                                rng.uniform(0.2, 0.5, n_fp)])
        fg = np.column_stack([p_car, (1 - p_car) * 0.3, (1 - p_car) * 0.2, (1 - p_car) * 0.1])
        var = (np.concatenate([sd[seen], np.full(n_fp, 0.5)])[:, None] ** 2
               * [1, 1, 0.2, 0.1, 0.05, 0.05, 0.1])
        ids = [f"{i}-{k}-{j}" for j in range(len(boxes))]
        heads.append(detection_array(h, boxes, fg, DEFAULT_CLASS_NAMES, ids=ids, variances=var))
        variances.append(box_variance_array(h, var, ids=ids))
    xyz = np.vstack([gt[:, :3] + rng.uniform(-0.8, 0.8, (n_obj, 3)) for _ in range(20)]
                    + [rng.uniform(-40, 40, (n_points, 3))]).astype(np.float32)
    cloud = create_xyz_cloud(h, xyz, rng.random(len(xyz)).astype(np.float32))
    return gt, heads, variances, cloud


def _train(settings, frames, out_dir, prefix):
    X, y = [], []
    for gt, heads, variances, cloud in frames:
        f = frame_features(heads, variances, settings, cloud)
        X.append(f.features)
        y.append(iou_3d(f.merge.boxes, gt).max(axis=1) if len(f) else np.zeros(0))
    X, y = np.vstack(X), np.concatenate(y)
    clf = fit_estimator("xgboost", "classification", X, (y >= 0.5).astype(float))
    reg = fit_estimator("xgboost", "regression", X, y)
    return save_pair(out_dir, prefix, clf, reg, settings.feature_names(),
                     training_data={"frames": len(frames), "source": "test_mimo_node"})


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """A models directory (LQ_MODELS_DIR layout) with small real xgboost pairs trained on
    pipeline features of synthetic multi-head frames, with and without point features."""
    root = tmp_path_factory.mktemp("mimo_models")
    frames = [make_frame(1000 + s) for s in range(10)]
    for use_points in (False, True):
        prefix = "mimo_points" if use_points else "mimo"
        _train(MimoSettings(use_points=use_points), frames, root / "mimo", prefix)
    return root


def params(model_dir, use_points=False, **extra):
    c, r = (model_dir / "mimo" / p.name for p in default_model_paths(use_points))
    return {"classifier_path": str(c), "regressor_path": str(r), "use_points": use_points,
            **extra}


class Rig:
    """The node under test with publishers for all its inputs and collectors on outputs."""

    def __init__(self, ros, model_dir, use_points=False, **extra):
        self.node = ros.start(MimoNode, parameters=params(model_dir, use_points, **extra))
        K = self.node.settings.num_heads
        self.heads = [ros.sensor_publisher(Detection3DArray, f"input/head_{k}") for k in range(K)]
        self.vars = ([ros.sensor_publisher(BoxVarianceArray, f"input/head_{k}/variance")
                      for k in range(K)] if self.node.use_variances else [])
        self.points = ros.sensor_publisher(PointCloud2, "input/points") if use_points else None
        self.dets = ros.collector(Detection3DArray, "output/detections")
        self.unc = ros.collector(ClusterUncertaintyArray, "output/uncertainty")
        self.markers = ros.collector(MarkerArray, "output/markers")
        for p in self.heads + self.vars + ([self.points] if self.points else []):
            assert ros.wait_for_match(p)
        for c in (self.dets, self.unc):
            assert ros.wait_for_match(c.subscription)

    def send(self, heads, variances=(), cloud=None, skip=()):
        """Publish a frame's messages and wait until the node received them (best-effort
        inputs with a depth of 5: a burst on a busy machine would lose some)."""
        sent = [(p, m) for k, (p, m) in enumerate(zip(self.heads, heads)) if k not in skip]
        sent += [(p, m) for k, (p, m) in enumerate(zip(self.vars, variances)) if k not in skip]
        if self.points is not None and cloud is not None:
            sent.append((self.points, cloud))
        before = {p.topic_name: received(self.node, p.topic_name) for p, _ in sent}
        for p, m in sent:
            p.publish(m)
        for topic, n in before.items():
            assert wait_until(lambda: received(self.node, topic) > n), topic


def received(node, topic):
    """Messages of ``topic`` (absolute or relative name) that reached the node's
    synchroniser. Not the diagnostics' count, taken as a message comes in: two executor
    threads decode at once, so a frame sent after that count rose could reach the
    synchroniser first and, 0.25 s of stamps later, declare a head stopped. Placeholders
    of a stopped input count too: send a resuming input alone (as the tests here do)."""
    return node.inputs.sync.stats().received[node.inputs.topics.index(topic.lstrip("/"))]


def by_stamp(msgs):
    return {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in msgs}


def stamp(i):
    h = header(i)
    return h.stamp.sec, h.stamp.nanosec


def test_parameters_and_inputs(ros, model_dir):
    node = ros.start(MimoNode, parameters=params(model_dir, num_heads=3))
    assert_declared_with_descriptions(node, {
        "num_heads", "eps", "voting", "min_cluster_size", "class_aware", "temperature",
        "use_variances", "use_points", "head_timeout", "classifier_path", "regressor_path",
        "class_names", "publish_markers", "input_type", "autoware_class_map",
        "min_confidence", "class_min_confidence", "range_min_confidence",
        "existence_fallback", "transform_inputs", "transform_tolerance",
        "output_scores", "sync_mode", "sync_slop",
        "sync_queue_size", "processing_queue_size", "diagnostics_period"})
    assert_yaml_matches_declared(node, "mimo_ros")
    assert node.inputs.topics == [f"input/head_{k}" for k in range(3)] + [
        f"input/head_{k}/variance" for k in range(3)]
    for t in node.inputs.topics:
        assert_sensor_qos(node, t)
    node2 = ros.start(MimoNode, parameters=params(model_dir, True, use_variances=False))
    assert node2.inputs.topics == ["input/head_0", "input/head_1", "input/points"]


@pytest.mark.parametrize("name,value,match", [
    ("num_heads", 0, "num_heads"), ("eps", 1.0, "eps"), ("voting", "majority", "voting"),
    ("temperature", 0.0, "temperature"), ("head_timeout", 0.0, "head_timeout"),
    ("class_names", ["car", "car"], "duplicates"), ("output_scores", "raw", "output_scores")])
def test_invalid_parameters_are_refused(ros, model_dir, name, value, match):
    with pytest.raises(Exception, match=match):
        ros.start(MimoNode, parameters=params(model_dir, **{name: value}))


def test_refuses_to_start_without_valid_models(ros, model_dir, tmp_path):
    with pytest.raises(RuntimeError, match="cannot load the MIMO meta models.*missing"):
        ros.start(MimoNode, parameters={"classifier_path": str(tmp_path / "missing.joblib"),
                                        "regressor_path": str(tmp_path / "missing.joblib")})
    # the points models (another feature schema, trained with use_points): refused, not misread
    c, r = (model_dir / "mimo" / p.name for p in default_model_paths(True))
    with pytest.raises(RuntimeError, match="use_points"):
        ros.start(MimoNode, parameters={"classifier_path": str(c), "regressor_path": str(r)})


def test_outputs_equal_pipeline_and_meta_models(ros, model_dir):
    rig = Rig(ros, model_dir, processing_queue_size=10)
    frames = [make_frame(i) for i in range(3)]
    for _, heads, variances, _ in frames:
        rig.send(heads, variances)
    assert rig.dets.wait_for(3) and rig.unc.wait_for(3) and rig.markers.wait_for(3)
    p = params(model_dir)
    settings = MimoSettings()
    models = MetaModels(p["classifier_path"], p["regressor_path"], settings.feature_names())
    dets, unc = by_stamp(rig.dets.messages), by_stamp(rig.unc.messages)
    for i, (_, heads, variances, _) in enumerate(frames):
        ref = process_frame(heads[0].header, heads, variances, settings, models)
        d, u = dets[stamp(i)], unc[stamp(i)]
        assert len(ref.frame) > 5 and len(d.detections) == len(ref.frame)
        assert [x.id for x in d.detections] == [x.id for x in ref.detections.detections]
        np.testing.assert_allclose([c.confidence for c in u.clusters], ref.confidence)
        np.testing.assert_allclose([c.predicted_iou for c in u.clusters], ref.predicted_iou)
        np.testing.assert_allclose([x.results[0].hypothesis.score for x in d.detections],
                                   ref.confidence)
        np.testing.assert_allclose(
            [[x.bbox.center.position.x, x.bbox.center.position.y, x.bbox.size.x]
             for x in d.detections], ref.frame.merge.boxes[:, [0, 1, 3]])
        np.testing.assert_allclose([c.aleatoric_total_variance for c in u.clusters],
                                   ref.frame.merge.stats.aleatoric_total_variance)
        assert u.confidence_model_id == models.confidence_model_id and u.iou_model_id
        assert d.header.frame_id == "lidar"
        # models without a training-data profile: the message says the monitor is off
        assert (u.version, u.drift_level) == (u.MESSAGE_VERSION, u.DRIFT_OFF)
        assert np.isnan(u.drift_score) and not u.passthrough
    assert 0.0 < np.mean([c.confidence for m in rig.unc.messages for c in m.clusters]) < 1.0
    assert rig.node.diag.dropped == 0


def test_stopped_head_fallback_and_recovery(ros, model_dir):
    rig = Rig(ros, model_dir, use_variances=False, head_timeout=0.25,
              processing_queue_size=20)
    node = rig.node
    frames = [make_frame(i) for i in range(14)]

    def send(i, skip=()):
        rig.send(frames[i][1], skip=skip)

    for i in range(3):
        send(i)
    assert rig.dets.wait_for(3)
    for i in range(3, 6):  # head 1 stops after frame 2: frames 3.. wait for it
        send(i, skip=(1,))
    assert not rig.dets.wait_for(4, timeout=0.3)
    # "now" is the second newest stamp (0.5 s): 0.5 - 0.2 s > head_timeout: merged without
    # head 1 from now on
    send(6, skip=(1,))
    assert rig.dets.wait_for(7)  # the waiting frames 3..6 came out
    assert "input/head_1 (subscribed as /input/head_1) sent nothing" in node.diag.status().message
    assert diag_values(node.diag.status())["inputs_stopped"] == "input/head_1"
    for i in range(7, 10):
        send(i, skip=(1,))
    send(10, skip=(0,))  # head 1 is back (first), then head 0 of the same frame
    assert wait_until(lambda: node.liveness.stopped == [])
    send(10, skip=(1,))
    for i in range(11, 14):
        send(i)
    assert rig.dets.wait_for(14, timeout=30) and rig.unc.wait_for(14, timeout=30), (
        sorted(by_stamp(rig.dets.messages)), node.inputs.sync.stats())
    assert wait_until(lambda: node.diag.status().message == "ok"), node.diag.status().message
    assert diag_values(node.diag.status())["inputs_stopped"] == "none"
    unc, dets = by_stamp(rig.unc.messages), by_stamp(rig.dets.messages)
    assert sorted(unc) == [stamp(i) for i in range(14)]
    settings = MimoSettings()
    for i in range(14):
        heads = frames[i][1]
        if 3 <= i < 10:
            heads = [heads[0], None]
        ref = frame_features(heads, None, settings)
        assert [d.id for d in dets[stamp(i)].detections] == ref.merged_ids()
        tops = {d.id.split(":")[0] for d in dets[stamp(i)].detections}
        sizes = [c.cluster_size for c in unc[stamp(i)].clusters]
        if 3 <= i < 10:  # one head, one vote: its boxes alone
            assert tops == {"0"} and len(sizes) == len(frames[i][1][0].detections) - sum(
                s - 1 for s in sizes)
        else:
            assert np.median(sizes) == 2
    values = diag_values(node.diag.status())
    assert int(values["frames_partial"]) == 7 and values["dropped"] == "0"


def test_variance_topics(ros, model_dir):
    rig = Rig(ros, model_dir, head_timeout=0.25, processing_queue_size=20)
    frames = [make_frame(i) for i in range(6)]
    rig.send(frames[0][1], frames[0][2])
    assert rig.unc.wait_for(1)
    u = rig.unc.messages[0]
    ref = frame_features(frames[0][1], frames[0][2], MimoSettings())
    atv = [c.aleatoric_total_variance for c in u.clusters]
    assert np.isfinite(atv).all()
    np.testing.assert_allclose(atv, ref.merge.stats.aleatoric_total_variance)
    # the variance topics stop: frames still come out, without aleatoric figures
    for i in range(1, 6):
        rig.send(frames[i][1])
    assert rig.unc.wait_for(6, timeout=10)
    last = by_stamp(rig.unc.messages)[stamp(5)]
    assert np.isnan([c.aleatoric_total_variance for c in last.clusters]).all()
    assert "variance (subscribed as /input/head_0/variance) sent nothing" in rig.node.diag.status().message


def test_points_input(ros, model_dir):
    rig = Rig(ros, model_dir, use_points=True, processing_queue_size=10)
    frames = [make_frame(i) for i in range(2)]
    for _, heads, variances, cloud in frames:
        rig.send(heads, variances, cloud)
    assert rig.unc.wait_for(2)
    p = params(model_dir, True)
    settings = MimoSettings(use_points=True)
    models = MetaModels(p["classifier_path"], p["regressor_path"], settings.feature_names())
    got = by_stamp(rig.unc.messages)
    for i, (_, heads, variances, cloud) in enumerate(frames):
        ref = process_frame(heads[0].header, heads, variances, settings, models, cloud_msg=cloud)
        assert np.isfinite(ref.frame.features[:, -5:]).all()
        np.testing.assert_allclose([c.confidence for c in got[stamp(i)].clusters],
                                   ref.confidence)
    assert "cloud_frame_id" not in rig.node.diag.warning_keys()
    # a cloud in another frame than the heads, no transform known: dropped, named
    _, heads, variances, cloud = make_frame(2)
    cloud_b = in_frame(cloud, T_BASE_LIDAR, "base_link")
    rig.send(heads, variances, cloud_b)
    assert wait_until(lambda: diag_values(rig.node.diag.status()).get("dropped.no_transform")
                      == "1")
    msg = rig.node.diag.status().message
    assert "'base_link' to 'lidar'" in msg and "at stamp 100.200000000 s" in msg
    # with base_link <- lidar on /tf_static the same scene gives the same outputs
    static = ros.publisher(TFMessage, "/tf_static", tf_static_qos())
    static.publish(tf_message("base_link", "lidar", T_BASE_LIDAR))
    assert wait_until(lambda: rig.node.tf.buffer.can_transform("lidar", "base_link"))
    _, heads, variances, cloud = make_frame(3)
    ref = process_frame(heads[0].header, heads, variances, settings, models, cloud_msg=cloud)
    rig.send(heads, variances, in_frame(cloud, T_BASE_LIDAR, "base_link"))
    assert rig.unc.wait_for(3)
    u = by_stamp(rig.unc.messages)[stamp(3)]
    assert u.header.frame_id == "lidar"
    # float32 CDR points: base_link coordinates rounded, moved back in float64
    np.testing.assert_allclose([c.confidence for c in u.clusters], ref.confidence, atol=1e-6)
    np.testing.assert_allclose([c.predicted_iou for c in u.clusters], ref.predicted_iou,
                               atol=1e-6)
    assert rig.node.diag.dropped == 1


#: base_link <- lidar: a roof mount 1.2 m ahead, 1.8 m up, turned by 0.3 rad
T_BASE_LIDAR = Transform.from_yaw(0.3, (1.2, 0.1, 1.8))


def in_frame(cloud, t, frame_id):
    """``cloud`` (x, y, z, intensity) with its points moved by ``t`` into ``frame_id``."""
    xyz, inten = xyz_intensity(cloud)
    h = Header(stamp=cloud.header.stamp, frame_id=frame_id)
    return create_xyz_cloud(h, t.apply_points(xyz).astype(np.float32), inten)


def tf_message(parent, child, t):
    ts = TransformStamped()
    ts.header.frame_id, ts.child_frame_id = parent, child
    v, r = ts.transform.translation, ts.transform.rotation
    v.x, v.y, v.z = t.translation.tolist()
    r.x, r.y, r.z, r.w = t.rotation.tolist()
    return TFMessage(transforms=[ts])


def test_heads_in_other_frames(ros, model_dir):
    """Head 1 in base_link (static transform on /tf_static): merged in head 0's frame, the
    outputs of the same scene published in one frame; a head in an unknown frame drops the
    frame (no_transform)."""
    static = ros.publisher(TFMessage, "/tf_static", tf_static_qos())
    static.publish(tf_message("base_link", "lidar", T_BASE_LIDAR))
    rig = Rig(ros, model_dir, use_variances=True)
    assert wait_until(lambda: rig.node.tf.buffer.can_transform("lidar", "base_link"))
    settings = MimoSettings()
    p = params(model_dir)
    models = MetaModels(p["classifier_path"], p["regressor_path"], settings.feature_names())
    _, heads, variances, _ = make_frame(4)
    ref = process_frame(heads[0].header, heads, variances, settings, models)
    moved = detections_in_frame(heads[1], T_BASE_LIDAR, "base_link")
    rig.send([heads[0], moved], variances)
    assert rig.unc.wait_for(1) and rig.dets.wait_for(1)
    u, d = rig.unc.messages[0], rig.dets.messages[0]
    assert u.header.frame_id == d.header.frame_id == "lidar"
    np.testing.assert_allclose([c.confidence for c in u.clusters], ref.confidence, atol=1e-9)
    np.testing.assert_allclose([c.predicted_iou for c in u.clusters], ref.predicted_iou,
                               atol=1e-9)
    assert [x.id for x in d.detections] == ref.frame.merged_ids()
    # a head in a frame nobody publishes: dropped, counted, named
    _, heads, variances, _ = make_frame(5)
    rig.send([heads[0], detections_in_frame(heads[1], T_BASE_LIDAR, "radar")], variances)
    assert wait_until(lambda: diag_values(rig.node.diag.status()).get("dropped.no_transform")
                      == "1")
    assert "head 1: no transform from 'radar' to 'lidar'" in rig.node.diag.status().message


def test_autoware_heads_in_base_link(ros, model_dir):
    """Acceptance (issue 19): two heads as DetectedObjects in base_link (variances beside
    them, named by index as Autoware objects have no ids) and the cloud in the lidar's frame
    (static base_link <- lidar on /tf_static) into mimo_node with point features:
    output/objects has one object per merged detection in the vision_msgs path's order,
    existence_probability = its confidence for the same scene, the merged x / y / z / yaw
    variances on the pose covariance with has_position_covariance."""
    from autoware_perception_msgs.msg import DetectedObjects
    from autoware_scenes import detected_objects, float32_scores

    static = ros.publisher(TFMessage, "/tf_static", tf_static_qos())
    static.publish(tf_message("base_link", "lidar", T_BASE_LIDAR))
    node = ros.start(MimoNode, parameters=params(model_dir, True, input_type="autoware",
                                                 processing_queue_size=10))
    assert wait_until(lambda: node.tf.buffer.can_transform("base_link", "lidar"))
    heads_pub = [ros.sensor_publisher(DetectedObjects, f"input/head_{k}") for k in range(2)]
    vars_pub = [ros.sensor_publisher(BoxVarianceArray, f"input/head_{k}/variance")
                for k in range(2)]
    points = ros.sensor_publisher(PointCloud2, "input/points")
    objects = ros.collector(DetectedObjects, "output/objects")
    unc = ros.collector(ClusterUncertaintyArray, "output/uncertainty")
    for p in heads_pub + vars_pub + [points]:
        assert ros.wait_for_match(p)
    assert ros.wait_for_match(objects.subscription) and ros.wait_for_match(unc.subscription)
    p = params(model_dir, True)
    settings = MimoSettings(use_points=True)
    models = MetaModels(p["classifier_path"], p["regressor_path"], settings.feature_names())
    confs = []
    for i in range(2):
        _, heads, variances, cloud = make_frame(i)
        heads = [detections_in_frame(float32_scores(h), T_BASE_LIDAR, "base_link")
                 for h in heads]
        for v in variances:  # (make_frame's messages share one Header object)
            v.header = Header(stamp=v.header.stamp, frame_id="base_link")
        assert cloud.header.frame_id == "lidar"
        # the same scene through the vision_msgs path, the cloud moved into base_link
        ref = process_frame(heads[0].header, heads, variances, settings, models,
                            cloud_msg=in_frame(cloud, T_BASE_LIDAR, "base_link"))
        assert not ref.frame.issues  # every variance entry used
        for v in variances:  # Autoware objects have no ids: entries named by index
            for e in v.variances:
                e.detection_id = str(e.detection_index)
        assert np.isfinite(ref.frame.features[:, -5:]).all()  # point features present
        confs.append(ref.confidence)
        for pub, h in zip(heads_pub, heads):
            pub.publish(detected_objects(h))
        for pub, v in zip(vars_pub, variances):
            pub.publish(v)
        points.publish(cloud)
        assert objects.wait_for(i + 1, timeout=15.0) and unc.wait_for(i + 1, 5.0)
        got = objects.messages[i]
        assert got.header == heads[0].header and len(got.objects) == len(ref.frame) > 5
        m = ref.frame.merge
        want = np.where(np.isnan(ref.confidence), m.scores, ref.confidence)
        # float32 on the wire; the cloud's points rounded in base_link for the reference
        np.testing.assert_allclose([o.existence_probability for o in got.objects], want,
                                   rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose([c.confidence for c in unc.messages[i].clusters],
                                   ref.confidence, atol=1e-6)
        pose = [o.kinematics.pose_with_covariance for o in got.objects]
        np.testing.assert_allclose([[q.pose.position.x, q.pose.position.y] for q in pose],
                                   m.boxes[:, :2])
        ref_cov = np.array([d.results[0].pose.covariance for d in ref.detections.detections])
        cov = np.array([q.covariance for q in pose])
        np.testing.assert_allclose(cov[:, [0, 7, 14, 35]], ref_cov[:, [0, 7, 14, 35]])
        assert (cov[:, [0, 7, 14]] > 0).all()
        assert all(o.kinematics.has_position_covariance for o in got.objects)
        top = [o.classification[0] for o in got.objects]
        np.testing.assert_allclose([c.probability for c in top], want, rtol=1e-6, atol=1e-6)
        labels = {"car": 1, "truck": 2, "pedestrian": 7, "cyclist": 6}
        assert [c.label for c in top] == [labels[x] for x in ref.frame.class_labels()]
    allc = np.concatenate(confs)
    assert allc.min() < 0.5 < allc.max()
    assert node.diag.dropped == 0


def test_malformed_heads_do_not_kill_the_node(ros, model_dir):
    rig = Rig(ros, model_dir, use_variances=False, processing_queue_size=10)
    _, heads, _, _ = make_frame(0)
    bad = [Detection3DArray(header=h.header, detections=list(h.detections)) for h in heads]
    bad[0].detections[0].bbox.center.position.x = float("nan")
    bad[0].detections[1].bbox.size.x = 0.0
    for r in bad[1].detections[0].results:
        r.hypothesis.class_id = "ufo"
    bad[1].detections[1].results = []
    rig.send(bad)
    assert rig.dets.wait_for(1)
    assert "unusable box(es)" in rig.node.diag.status().message
    # thousands of boxes per head (most of them overlapping junk)
    rng = np.random.default_rng(5)
    h = header(1)
    many = []
    for k in range(2):
        b = np.column_stack([rng.uniform(0, 60, (3000, 2)), np.full(3000, -0.9),
                             np.tile([4.0, 1.8, 1.5], (3000, 1)), rng.uniform(-3, 3, 3000)])
        fg = np.tile([0.6, 0.1, 0.1, 0.1], (3000, 1))
        many.append(detection_array(h, b, fg, DEFAULT_CLASS_NAMES))
    rig.send(many)
    assert rig.dets.wait_for(2, timeout=30)
    # and a normal frame afterwards
    _, heads, _, _ = make_frame(2)
    rig.send(heads)
    assert rig.dets.wait_for(3, timeout=10)
    assert len(rig.dets.messages[-1].detections) > 5
    assert wait_until(lambda: rig.node.diag.status().message == "ok"), rig.node.diag.status().message
    assert "dropped.processing_error" not in diag_values(rig.node.diag.status())


def test_executable_starts_and_stops_cleanly(ros, model_dir, monkeypatch):
    monkeypatch.setenv("LQ_MODELS_DIR", str(model_dir))  # the default model paths
    run_executable_and_signal(ros, "mimo_ros", "mimo_node",
                              ["input/head_0", "input/head_1", "input/head_0/variance",
                               "input/head_1/variance"], "SIGTERM")


def test_executable_without_models_exits_with_code_2(ros, tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_MODELS_DIR", str(tmp_path))
    proc = ros.spawn([str(executable("mimo_ros", "mimo_node"))],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2, out
    assert "node failed to start" in out and "meta models" in out


def test_bad_parameter_exits_with_code_2(ros):
    proc = ros.spawn([str(executable("mimo_ros", "mimo_node")), "--ros-args", "-p",
                      "num_heads:=0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                     text=True)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2, out
    assert "node failed to start" in out and "num_heads" in out


def test_launch_file():
    from node_shell_checks import assert_launch_file
    assert_launch_file("mimo_ros", "mimo_node")


def test_one_future_stamped_message_costs_at_most_its_frame(ros, model_dir):
    # issue 14 repro: one head_0/variance stamped 0.8 s ahead left 1 of the next 10 valid
    # frames out (it took that stamp as "now" and declared every other input stopped)
    rig = Rig(ros, model_dir, head_timeout=0.5, processing_queue_size=20)
    frames = [make_frame(i) for i in range(12)]
    rig.send(frames[0][1], frames[0][2])
    assert rig.dets.wait_for(1)
    bad = box_variance_array(header(1 + 8), np.zeros((0, 7)), ids=[])  # stamped 0.8 s ahead
    before = received(rig.node, "input/head_0/variance")
    rig.vars[0].publish(bad)
    assert wait_until(lambda: received(rig.node, "input/head_0/variance") > before)
    for i in range(1, 11):
        rig.send(frames[i][1], frames[i][2])
    assert rig.dets.wait_for(11, timeout=20), len(rig.dets.messages)
    assert sorted(by_stamp(rig.dets.messages)) == [stamp(i) for i in range(11)]
    assert rig.node.liveness.stopped == []
    assert diag_values(rig.node.diag.status())["inputs_stopped"] == "none"
