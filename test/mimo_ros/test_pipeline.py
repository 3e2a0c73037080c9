"""mimo_ros.pipeline: head messages -> merged detections, features, outputs; head fallback."""
import numpy as np
import pytest
from lidar_quality_core.box_variance_cdr import decode_box_variance_array
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.meta_model import MetaModels, fit_estimator, save_pair
from lidar_quality_core.pointcloud import create_xyz_cloud
from lidar_quality_core.mimo.merging import HeadDetections, MergeConfig, merge_heads
from lidar_quality_core.parameters import from_parameters
from lidar_quality_core.transforms import NoTransformError, Transform, TransformBuffer
from mimo_ros.pipeline import (DEFAULT_CLASS_NAMES, POINT_FEATURES, STAT_FEATURES,
                               InputLiveness, MimoSettings, default_model_paths,
                               frame_features, head_detections, output_messages,
                               process_frame, MimoProcessor,
                               NoHeadError)
from reference_perception.messages import box_variance_array, detection_array
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header

NAMES = DEFAULT_CLASS_NAMES
F = {n: i for i, n in enumerate(STAT_FEATURES)}


def header(sec=1):
    h = Header(frame_id="lidar")
    h.stamp.sec = sec
    return h


def probs(rows):
    """Foreground probabilities (n, 4) from rows of (label column, probability)."""
    out = np.full((len(rows), 4), 0.0)
    for i, (c, p) in enumerate(rows):
        out[i] = (1.0 - p) / 5.0
        out[i, c] = p
    return out


BOXES = np.array([[10.0, 2.0, -0.8, 4.5, 1.9, 1.6, 0.3],
                  [25.0, -6.0, -0.9, 0.8, 0.7, 1.8, -2.0],
                  [-15.0, 8.0, -1.0, 1.8, 0.7, 1.7, 3.1]])
FG = probs([(0, 0.8), (2, 0.6), (3, 0.7)])
VAR = np.tile([0.04, 0.05, 0.01, 0.02, 0.01, 0.01, 0.003], (3, 1))


def head_msg(boxes=BOXES, fg=FG, var=VAR, ids=None):
    return detection_array(header(), boxes, fg, NAMES, ids=ids, variances=var)


def var_msg(var=VAR, ids=None):
    return box_variance_array(header(), var, ids=ids)


def full_probs(fg):
    return np.column_stack([np.clip(1 - fg.sum(axis=1), 0, 1), fg])


def test_identical_heads_give_zero_mi_and_etv():
    s = MimoSettings()
    f = frame_features([head_msg(), head_msg()], [var_msg(), var_msg()], s)
    assert f.features.shape == (3, len(s.feature_names())) and s.feature_names() == STAT_FEATURES
    assert np.all(f.features[:, F["cluster_size"]] == 2)
    assert np.all(f.features[:, F["head_fraction"]] == 1.0)
    assert np.all(f.features[:, F["mutual_information"]] == 0.0)
    assert np.all(f.features[:, F["epistemic_total_variance"]] == 0.0)
    np.testing.assert_allclose(f.features[:, F["aleatoric_total_variance"]], VAR.sum(axis=1))
    assert f.heads_used == [0, 1] and not f.issues


def test_merged_frame_equals_merge_heads_on_the_arrays():
    rng = np.random.default_rng(0)
    boxes = [BOXES + rng.normal(0, 0.1, BOXES.shape) * [1, 1, 0.2, 0.1, 0.1, 0.1, 0.1]
             for _ in range(2)]
    fg = [probs([(0, 0.8), (2, 0.6), (3, 0.7)]), probs([(0, 0.7), (1, 0.5), (3, 0.9)])]
    var = [VAR, VAR * 2]
    s = MimoSettings()
    f = frame_features([head_msg(b, p, v) for b, p, v in zip(boxes, fg, var)],
                       [var_msg(v) for v in var], s)
    ref = merge_heads([HeadDetections(b, full_probs(p), v) for b, p, v in zip(boxes, fg, var)],
                      MergeConfig(score_type="probabilities", background_index=0))
    m = f.merge
    np.testing.assert_allclose(m.boxes, ref.boxes, atol=1e-12)
    np.testing.assert_allclose(m.class_probs, ref.class_probs, atol=1e-12)
    np.testing.assert_array_equal(m.labels, ref.labels)
    st = ref.stats
    X = f.features
    np.testing.assert_allclose(X[:, F["shannon_entropy"]], st.shannon_entropy, atol=1e-12)
    np.testing.assert_allclose(X[:, F["mutual_information"]], st.mutual_information, atol=1e-12)
    np.testing.assert_allclose(X[:, F["epistemic_total_variance"]], st.epistemic_total_variance)
    np.testing.assert_allclose(X[:, F["aleatoric_total_variance"]], st.aleatoric_total_variance)
    np.testing.assert_allclose(X[:, F["epistemic_var_x"]:F["epistemic_var_yaw"] + 1],
                               st.epistemic_variance)
    np.testing.assert_allclose(X[:, F["score"]], ref.scores)
    np.testing.assert_array_equal(X[:, F["class"]], ref.labels - 1)
    np.testing.assert_allclose(X[:, F["distance"]], np.hypot(*ref.boxes[:, :2].T))
    # ids and classes of the top members
    assert f.class_labels() == [NAMES[c - 1] for c in ref.labels]
    top = ref.top_member
    assert f.merged_ids() == [f"{ref.member_head[t]}:{ref.member_index[t]}" for t in top]


def test_missing_head_merges_the_heads_present():
    s = MimoSettings(num_heads=3)  # consensus over 3 needs 2 votes; over the 2 present too
    one_box = BOXES[:1]
    f = frame_features([head_msg(ids=[7, 8, 9]), None, head_msg(one_box, FG[:1], VAR[:1])],
                       None, s)
    assert f.heads_used == [0, 2] and f.merge.num_heads == 2 and f.merge.min_samples == 2
    assert len(f) == 1 and f.merged_ids() == ["0:7"] and f.top_heads().tolist() == [0]
    np.testing.assert_allclose(f.features[:, F["head_fraction"]], 1.0)
    # one head left: its boxes are clusters of their own (K = 1, one vote)
    f1 = frame_features([None, head_msg(), None], None, s)
    assert f1.heads_used == [1] and len(f1) == 3 and f1.top_heads().tolist() == [1, 1, 1]
    np.testing.assert_allclose(f1.merge.boxes, BOXES, atol=1e-12)
    with pytest.raises(ValueError, match="no head"):
        frame_features([None, None, None], None, s)
    with pytest.raises(ValueError, match="num_heads"):
        frame_features([head_msg()], None, s)


def test_without_variances_the_aleatoric_figures_are_nan():
    f = frame_features([head_msg(), head_msg(BOXES + [0.1, 0, 0, 0, 0, 0, 0])], None,
                       MimoSettings())
    assert len(f) == 3
    X = f.features
    assert np.isnan(X[:, F["aleatoric_total_variance"]]).all()
    assert np.isnan(X[:, F["aleatoric_var_x"]:F["aleatoric_var_yaw"] + 1]).all()
    np.testing.assert_allclose(X[:, F["epistemic_var_x"]], 0.0025)  # (0.1 m / 2)^2
    np.testing.assert_allclose(X[:, F["epistemic_total_variance"]], 0.0025)
    # the covariance falls back to the epistemic variance (a lower bound), never NaN
    dets, unc = output_messages(header(), f, np.full(3, 0.5), np.full(3, 0.6))
    cov = np.array(dets.detections[0].results[0].pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(np.diag(cov), [0.0025, 0, 0, 0, 0, 0], atol=1e-12)
    assert np.isnan(unc.clusters[0].aleatoric_total_variance)


def test_variance_entries_are_matched_by_index_and_id():
    a = detections_to_arrays(head_msg(ids=[5, 6, 7]))
    assert a.ids == ["5", "6", "7"]
    v = var_msg(ids=[5, 99, 7])  # entry 1 names another detection
    v.variances[2].x = -1.0      # a negative variance
    issues = []
    hd, _ = head_detections(head_msg(ids=[5, 6, 7]), v, MimoSettings(), issues=issues)
    np.testing.assert_allclose(hd.variances[0], VAR[0])
    assert np.isnan(hd.variances[1]).all()
    assert np.isnan(hd.variances[2, 0]) and np.allclose(hd.variances[2, 1:], VAR[2, 1:])
    assert any("2 variance entries ignored" in t for t in issues)


def test_variance_entries_without_id_or_out_of_range_index():
    """An empty id matches by index alone; an index past the detections matches nothing;
    decoded bytes match as the message does."""
    v = var_msg(ids=[5, 6, 7])
    v.variances[0].detection_id = ""        # by index: detection 0
    v.variances[1].detection_index = 3      # no detection 3 (of 3)
    for msg in (v, decode_box_variance_array(serialize_message(v))):
        issues = []
        hd, _ = head_detections(head_msg(ids=[5, 6, 7]), msg, MimoSettings(), issues=issues)
        np.testing.assert_allclose(hd.variances[[0, 2]], VAR[[0, 2]])
        assert np.isnan(hd.variances[1]).all()
        assert any("1 variance entry ignored" in t for t in issues)


def test_variance_entries_in_order_or_permuted_match_alike():
    """Entries in detection order (the usual message) and the same entries reordered
    give each detection its own variances."""
    v = var_msg(ids=[5, 6, 7])
    hd, _ = head_detections(head_msg(ids=[5, 6, 7]), v, MimoSettings(), issues=[])
    np.testing.assert_allclose(hd.variances, VAR)
    v.variances = [v.variances[k] for k in (2, 0, 1)]
    for msg in (v, decode_box_variance_array(serialize_message(v))):
        issues = []
        hd, _ = head_detections(head_msg(ids=[5, 6, 7]), msg, MimoSettings(), issues=issues)
        np.testing.assert_allclose(hd.variances, VAR)
        assert not issues
    # in order by index, but one id names another detection: that entry is ignored
    v = var_msg(ids=[5, 6, 8])
    issues = []
    hd, _ = head_detections(head_msg(ids=[5, 6, 7]), v, MimoSettings(), issues=issues)
    assert np.isnan(hd.variances[2]).all() and any("1 variance entry" in t for t in issues)


def test_class_distribution_conversion():
    hd, a = head_detections(head_msg(), None, MimoSettings())
    np.testing.assert_allclose(hd.class_scores, full_probs(FG))
    # already decoded arrays (e.g. from serialized bytes) give the same
    hd2, a2 = head_detections(detections_to_arrays(head_msg()), None, MimoSettings())
    np.testing.assert_array_equal(hd2.class_scores, hd.class_scores)
    np.testing.assert_array_equal(hd2.boxes, hd.boxes)
    # a class without hypothesis is probability 0; unknown classes are ignored
    m = head_msg()
    m.detections[0].results = m.detections[0].results[:1]  # car 0.8 only
    m.detections[1].results[0].hypothesis.class_id = "bus"  # pedestrian 0.6 -> unknown
    hd, _ = head_detections(m, None, MimoSettings())
    np.testing.assert_allclose(hd.class_scores[0], [0.2, 0.8, 0, 0, 0])
    np.testing.assert_allclose(hd.class_scores[1, 3], 0.0)
    np.testing.assert_allclose(hd.class_scores[1].sum(), 1.0)  # background took the 0.6


def test_malformed_boxes_are_left_out_and_reported():
    boxes = np.vstack([BOXES, BOXES[:1] * [1, 1, 1, 1, 1, 1, 1]])
    boxes[0, 0] = np.nan        # NaN centre
    boxes[1, 3] = 0.0           # zero length
    fg = np.vstack([FG, FG[:1]])
    m = head_msg(boxes, fg, None)
    for r in m.detections[2].results:
        r.hypothesis.class_id = "ufo"  # no known class
    m.detections[3].results[0].hypothesis.score = 1.5  # not a probability
    issues = []
    hd, a = head_detections(m, None, MimoSettings(), issues=issues)
    assert np.isnan(hd.class_scores).all(axis=1).tolist() == [True] * 4
    assert issues[0] == ("4 unusable box(es): #0: non-finite centre, #1: size <= 0, "
                         "#2: no hypothesis of a known class, #3: class score outside [0, 1]")
    f = frame_features([m, head_msg()], None, MimoSettings())
    assert len(f) == 0 and f.features.shape == (0, len(STAT_FEATURES))
    assert all(t.startswith("head 0:") for t in f.issues)


def test_points_features_of_the_merged_box():
    from lidar_quality_core.lmd.features import OWN_QUANTITIES, compute_features

    rng = np.random.default_rng(1)
    xyz = np.vstack([BOXES[0, :3] + rng.uniform(-0.5, 0.5, (40, 3)),
                     rng.uniform(-50, 50, (500, 3))]).astype(np.float32)
    inten = rng.uniform(0, 1, len(xyz)).astype(np.float32)
    xyz[[3, 100]] = np.nan  # unusable points count nowhere, in LMD and here alike
    inten[5] = np.inf
    s = MimoSettings(use_points=True)
    assert s.feature_names() == STAT_FEATURES + POINT_FEATURES
    cloud = create_xyz_cloud(header(), xyz, inten)
    f = frame_features([head_msg(), head_msg()], None, s, cloud)
    ref = compute_features(xyz, inten, f.merge.boxes, f.merge.scores, f.merge.labels - 1,
                           mode="none")[:, [OWN_QUANTITIES.index(n) for n in POINT_FEATURES]]
    np.testing.assert_array_equal(f.features[:, len(STAT_FEATURES):], ref)  # bit for bit
    assert f.features[0, len(STAT_FEATURES)] >= 37
    # the same from arrays; no intensity: counts stay, reflectance unknown
    g = frame_features([head_msg(), head_msg()], None, s, (xyz, None))
    ref0 = compute_features(xyz, np.zeros(len(xyz)), f.merge.boxes, f.merge.scores,
                            f.merge.labels - 1, mode="none")
    np.testing.assert_array_equal(g.features[:, -5:-3], ref0[:, [12, 13]])
    assert np.isnan(g.features[:, -3:]).all()
    # no cloud at all: NaN point features
    assert np.isnan(frame_features([head_msg(), head_msg()], None, s).features[:, -5:]).all()
    # an organized cloud's (0, 0, 0) padding is no point (it counted in |X| before)
    padded = np.vstack([xyz, np.zeros((300, 3), np.float32)])
    p = frame_features([head_msg(), head_msg()], None, s,
                       (padded, np.concatenate([inten, np.full(300, 0.5, np.float32)])))
    np.testing.assert_array_equal(p.features, f.features)


def test_settings_validation_and_model_paths():
    MimoSettings().validate()
    for bad in (MimoSettings(num_heads=0), MimoSettings(merge=MergeConfig()),
                MimoSettings(class_names=()), MimoSettings(class_names=("car", "car"))):
        with pytest.raises(ValueError):
            bad.validate()
    c, r = default_model_paths(False)
    assert c.name == "mimo_classifier.joblib" and r.name == "mimo_regressor.joblib"
    assert c.parent.name == "mimo"
    assert default_model_paths(True)[0].name == "mimo_points_classifier.joblib"


def test_min_cluster_size_above_the_head_count_is_refused():
    """min_cluster_size 3 with 2 heads was accepted and dropped almost every object."""
    with pytest.raises(ValueError, match=r"min_cluster_size 3 > num_heads 2: .* unanimous K"):
        MimoSettings(num_heads=2, merge=MergeConfig(
            score_type="probabilities", min_cluster_size=3)).validate()
    p = dict(num_heads=3, eps=0.5, voting="consensus", min_cluster_size=4, class_aware=False,
             temperature=1.0, use_points=False, class_names=list(NAMES))
    with pytest.raises(ValueError, match="min_cluster_size 4 > num_heads 3"):
        from_parameters(MimoSettings, p).validate()
    for m in (0, 1, 3):
        s = from_parameters(MimoSettings, {**p, "min_cluster_size": m})
        s.validate()
        assert s.num_heads == 3 and s.merge.min_cluster_size == (m or None)
        assert s.merge.score_type == "probabilities" and s.merge.background_index == 0


def test_head_in_another_frame_is_reported_and_merged():
    other = head_msg()
    other.header.frame_id = "base_link"
    f = frame_features([head_msg(), other], None, MimoSettings())
    assert f.issues == ["head 1 frame_id 'base_link' differs from head 0 'lidar' "
                        "(merged as if equal)"]
    same = frame_features([head_msg(), head_msg()], None, MimoSettings())
    np.testing.assert_array_equal(f.features, same.features)
    assert same.issues == []
    # the first head present is the reference; decoded heads and the cloud count too
    from lidar_quality_core.detection_cdr import decode_detection_array
    from rclpy.serialization import serialize_message

    f = frame_features([None, decode_detection_array(serialize_message(other)), head_msg()],
                       None, MimoSettings(num_heads=3),
                       create_xyz_cloud(header(), BOXES[:, :3]))
    assert f.issues == [
        "head 2 frame_id 'lidar' differs from head 1 'base_link' (merged as if equal)",
        "input/points frame_id 'lidar' differs from head 1 'base_link' (merged as if equal)"]


def test_tilted_head_boxes_are_merged_upright_and_reported():
    """30 deg roll on one head's box was dropped without a word."""
    m = head_msg()
    o = m.detections[0].bbox.center.orientation
    half_roll, half_yaw = np.radians(30) / 2, BOXES[0, 6] / 2
    # Rz(yaw) Rx(roll): x, y, z, w
    o.x, o.y = np.sin(half_roll) * np.cos(half_yaw), np.sin(half_roll) * np.sin(half_yaw)
    o.z, o.w = np.cos(half_roll) * np.sin(half_yaw), np.cos(half_roll) * np.cos(half_yaw)
    f = frame_features([head_msg(), m], None, MimoSettings())
    assert f.issues == ["head 1: 1 of 3 boxes have roll/pitch up to 30.0 deg: only yaw is "
                        "used (boxes are read as upright)"]
    np.testing.assert_allclose(f.features, frame_features([head_msg(), head_msg()], None,
                                                          MimoSettings()).features,
                               rtol=1e-12, atol=1e-12)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Small real models (linear) on the features of a few perturbed frames."""
    s = MimoSettings()
    rng = np.random.default_rng(2)
    X, y_cls, y_iou = [], [], []
    for i in range(12):
        jitter = [1, 1, 0, 0, 0, 0, 0]
        heads = [head_msg(BOXES + rng.normal(0, 0.02 * (1 + i % 4), BOXES.shape) * jitter)
                 for _ in range(2)]
        f = frame_features(heads, None, s)
        X.append(f.features)
        d = np.linalg.norm(f.merge.boxes[:, None, :2] - BOXES[None, :, :2], axis=2).min(axis=1)
        y_iou.append(np.clip(1 - d, 0, 1))
        y_cls.append((d < 0.04).astype(float))
    X, y_cls, y_iou = np.vstack(X), np.concatenate(y_cls), np.concatenate(y_iou)
    y_cls[:2] = [0, 1]
    clf = fit_estimator("linear", "classification", X, y_cls)
    reg = fit_estimator("linear", "regression", X, y_iou)
    c, r = save_pair(tmp_path_factory.mktemp("mimo_models"), "mimo", clf, reg, s.feature_names())
    return MetaModels(c, r, s.feature_names())


def test_process_frame_outputs(models):
    s = MimoSettings()
    h = header(3)
    heads = [head_msg(BOXES + [0.05, 0, 0, 0, 0, 0, 0]), head_msg(ids=[3, 4, 5])]
    variances = [var_msg(), var_msg(VAR * 2, ids=[3, 4, 5])]
    out = process_frame(h, heads, variances, s, models)
    f = frame_features(heads, variances, s)
    assert not f.issues
    conf, iou = models.predict(f.features)
    np.testing.assert_array_equal(out.confidence, conf)
    np.testing.assert_array_equal(out.predicted_iou, iou)
    dets, unc = out.detections, out.uncertainty
    assert dets.header.stamp.sec == 3 and unc.header.stamp.sec == 3
    assert unc.confidence_model_id == models.confidence_model_id
    # no drift check asked for (domain None): the message says the monitor is off
    assert (unc.version, unc.drift_level) == (unc.MESSAGE_VERSION, unc.DRIFT_OFF)
    assert np.isnan(unc.drift_score) and unc.drift_window_frames == 0
    assert unc.drift_quantities == "" and not unc.passthrough
    ids = [d.id for d in dets.detections]
    assert ids == f.merged_ids() == [c.detection_id for c in unc.clusters]
    for i, d in enumerate(dets.detections):
        sc = [r.hypothesis.score for r in d.results]
        assert sc == sorted(sc, reverse=True) and len(sc) == 4
        assert d.results[0].hypothesis.class_id == f.class_labels()[i]
        assert sc[0] == pytest.approx(conf[i])
        # ratios are the merged distribution's
        p = f.merge.class_probs[i, 1:]
        by_name = {r.hypothesis.class_id: r.hypothesis.score for r in d.results}
        np.testing.assert_allclose([by_name[n] for n in NAMES], p * conf[i] / p.max())
        cov = np.diag(np.array(d.results[0].pose.covariance).reshape(6, 6))
        pv = f.merge.stats.predictive_variance[i]
        np.testing.assert_allclose(cov[[0, 1, 2, 5]], pv[[0, 1, 2, 6]])
        c = unc.clusters[i]
        assert c.detection_index == i and c.cluster_size == 2
        assert c.confidence == conf[i] and c.predicted_iou == iou[i]
    np.testing.assert_allclose(
        [[d.bbox.center.position.x, d.bbox.size.x] for d in dets.detections],
        f.merge.boxes[:, [0, 3]])
    # the node's serialized form is the same message
    from rclpy.serialization import deserialize_message
    from vision_msgs.msg import Detection3DArray

    ser = process_frame(h, heads, variances, s, models, serialized=True)
    back = deserialize_message(ser.detections, Detection3DArray)
    assert back.header == dets.header
    assert [(d.id, d.bbox, [(r.hypothesis.class_id, r.hypothesis.score) for r in d.results])
            for d in back.detections] == [
        (d.id, d.bbox, [(r.hypothesis.class_id, r.hypothesis.score) for r in d.results])
        for d in dets.detections]
    np.testing.assert_array_equal(back.detections[0].results[1].pose.covariance,
                                  dets.detections[0].results[1].pose.covariance)
    # so is the node's serialized uncertainty message (NaN ATV without variances: NaN-equal)
    from lidar_quality_msgs.msg import ClusterUncertainty, ClusterUncertaintyArray
    for var in (variances, None):
        msg = process_frame(h, heads, var, s, models).uncertainty
        raw = process_frame(h, heads, var, s, models, serialized_uncertainty=True).uncertainty
        back = deserialize_message(raw, ClusterUncertaintyArray)
        assert back.header == msg.header and len(back.clusters) == len(msg.clusters) > 0
        for k in ("confidence_model_id", "iou_model_id", "version", "drift_level",
                  "drift_window_frames", "drift_quantities", "passthrough"):
            assert getattr(back, k) == getattr(msg, k), k
        fields = list(ClusterUncertainty.get_fields_and_field_types())
        for a, b in zip(back.clusters, msg.clusters):
            for k in fields:
                np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    # unscaled scores on request
    dets2, _ = output_messages(h, f, conf, iou, scores="merged")
    assert dets2.detections[0].results[0].hypothesis.score == pytest.approx(f.merge.scores[0])


def test_thresholds_filter_the_detections_not_the_uncertainty(models):
    from lidar_quality_core.thresholds import ConfidenceThresholds
    s = MimoSettings()
    heads = [head_msg(BOXES + [0.05, 0, 0, 0, 0, 0, 0]), head_msg(ids=[3, 4, 5])]
    full = process_frame(header(3), heads, None, s, models)
    conf = full.confidence
    cut = float(np.sort(conf)[1])  # removes the lowest one or more
    th = ConfidenceThresholds(floor=cut)
    out = process_frame(header(3), heads, None, s, models, thresholds=th, serialized=True)
    kept = conf >= cut
    assert out.kept.tolist() == kept.tolist() and 0 < kept.sum() < len(conf)
    from rclpy.serialization import deserialize_message
    from vision_msgs.msg import Detection3DArray
    dets = deserialize_message(out.detections, Detection3DArray)
    ids = out.frame.merged_ids()
    assert [d.id for d in dets.detections] == [ids[i] for i in np.flatnonzero(kept)]
    assert [c.detection_id for c in out.uncertainty.clusters] == ids  # every merged one
    labels = out.frame.class_labels()
    assert sum(out.removed.values()) == int((~kept).sum())
    assert set(out.removed) == {f"removed.{labels[i]}.all" for i in np.flatnonzero(~kept)}


# ------------------------------------------------------------------ InputLiveness
S = 1_000_000_000


def test_liveness_declares_a_silent_input_stopped_and_recovers():
    lv = InputLiveness(2, timeout_ns=S // 2)
    for t in range(3):  # both inputs publish: nothing to do
        assert lv.arrival(0, t * S // 10).placeholders == []
        assert lv.arrival(1, t * S // 10).placeholders == []
    # input 1 goes silent; stamps 0.3 and 0.4 wait, 0.5 is still within the timeout
    for t in (3, 4, 5, 6):
        a = lv.arrival(0, t * S // 10, last_matched_ns=2 * S // 10)
        assert a.stopped == [] and a.placeholders == []
    # one message 0.6 s ahead is not enough evidence ("now" is the second newest stamp)
    a = lv.arrival(0, 8 * S // 10, last_matched_ns=2 * S // 10)
    assert a.stopped == []
    a = lv.arrival(0, 9 * S // 10, last_matched_ns=2 * S // 10)  # 0.8 - 0.2 > 0.5
    assert a.stopped == [1] and lv.stopped == [1]
    assert a.placeholders == [(1, t * S // 10) for t in (3, 4, 5, 6, 8, 9)]  # the waiting ones
    a = lv.arrival(0, 10 * S // 10, last_matched_ns=9 * S // 10)
    assert a.placeholders == [(1, 10 * S // 10)]
    # input 1 is back: live again, no more placeholders
    a = lv.arrival(1, 11 * S // 10, last_matched_ns=10 * S // 10)
    assert a.resumed == [1] and lv.stopped == []
    assert lv.arrival(0, 11 * S // 10, last_matched_ns=10 * S // 10).placeholders == []


def test_liveness_never_seen_input_and_reset():
    lv = InputLiveness(3, timeout_ns=S)
    lv.arrival(0, 10 * S)
    lv.arrival(1, 10 * S)
    assert lv.arrival(0, 11 * S + 1, last_matched_ns=None).stopped == []
    a = lv.arrival(0, 11 * S + 2, last_matched_ns=None)
    assert a.stopped == [1, 2]  # 2 never sent anything; 1 is also > 1 s behind
    assert (2, 11 * S + 1) in a.placeholders
    # a looped bag: stamps jump back, everything is forgotten
    a = lv.arrival(0, 2 * S)
    assert a.resumed == [1, 2] and lv.stopped == [] and a.placeholders == []


def test_liveness_approximate_mode_one_placeholder_per_frame():
    lv = InputLiveness(3, timeout_ns=S // 2, slop_ns=S // 100)
    lv.arrival(0, 0)
    lv.arrival(1, 1000)
    lv.arrival(2, 2000)
    got = []
    for k in range(1, 10):
        t = k * S // 10
        got += lv.arrival(0, t).placeholders
        got += lv.arrival(1, t + 3_000_000).placeholders  # 3 ms later, same frame
    assert [j for j, _ in got] == [2] * len({s // (S // 10) for _, s in got})


def test_liveness_one_future_stamp_stops_nothing():
    # 2 heads + 2 variance inputs at 10 Hz; one variance message stamped 0.8 s ahead
    lv = InputLiveness(4, timeout_ns=S // 2)
    changes = []
    for k in range(20):
        t = k * S // 10
        for j in range(4):
            stamp = t + 8 * S // 10 if (k, j) == (5, 2) else t
            a = lv.arrival(j, stamp, last_matched_ns=t - S // 10 if k else None)
            changes += a.stopped + a.resumed + [p[0] for p in a.placeholders]
    assert changes == [] and lv.stopped == []


def test_liveness_short_loop_resets():
    # a 0.4 s bag looped: the jump back is below reset_ns, but every input goes back
    lv = InputLiveness(2, timeout_ns=S // 2)
    for t in range(5):
        for j in range(2):
            lv.arrival(j, t * S // 10)
    assert lv.arrival(0, 0).resumed == [] and lv._newest[0] == 4 * S // 10
    lv.arrival(1, 0)  # both went back: everything forgotten
    assert lv._newest == [None, 0]
    for t in range(1, 5):  # and the second pass runs as the first did
        for j in range(2):
            a = lv.arrival(j, t * S // 10)
            assert a.stopped == [] and a.placeholders == []


def test_processor_is_the_node_frame_contract(models, tmp_path):
    s = MimoSettings()
    proc = MimoProcessor(s, models)
    heads = [head_msg(BOXES + [0.05, 0, 0, 0, 0, 0, 0]), head_msg(ids=[3, 4, 5])]
    res = proc.process(heads, None, markers=True)
    ref = process_frame(heads[0].header, heads, None, s, models, serialized=True)
    assert bytes(res.out.detections) == bytes(ref.detections)
    np.testing.assert_array_equal(res.out.confidence, ref.confidence)
    assert res.issues == {} and res.counts == {"boxes.in": 6, "detections.out": len(ref.frame),
                                               "frames_partial": 0}
    assert len(res.markers.markers) >= len(ref.frame)
    assert proc.process([heads[0], None]).counts["frames_partial"] == 1
    with pytest.raises(NoHeadError):
        proc.process([None, None])
    with pytest.raises(ValueError, match="scores"):
        MimoProcessor(s, models, scores="fancy")
    # with points: a malformed cloud costs the point features; another frame is said
    sp = MimoSettings(use_points=True)
    f = frame_features(heads, None, sp, (np.zeros((10, 3), np.float32), np.zeros(10, np.float32)))
    X = np.vstack([f.features] * 4)
    X[:, -5] = np.arange(len(X))
    clf = fit_estimator("linear", "classification", X, (np.arange(len(X)) % 2).astype(float))
    reg = fit_estimator("linear", "regression", X, np.linspace(0, 1, len(X)))
    c, r = save_pair(tmp_path, "mimo_points", clf, reg, sp.feature_names())
    pproc = MimoProcessor(sp, MetaModels(c, r, sp.feature_names()), transform_inputs=False)
    xyz = np.zeros((20, 3), np.float32)
    cloud = create_xyz_cloud(heads[0].header, xyz, np.ones(20, np.float32))
    cloud.header = Header(stamp=cloud.header.stamp, frame_id="base_link")
    res = pproc.process(heads, None, cloud)
    assert "cloud_frame_id" in res.issues and "'base_link'" in res.issues["cloud_frame_id"]
    cloud.data = cloud.data[:7]
    res = pproc.process(heads, None, cloud)
    assert "cloud" in res.issues and np.isnan(res.out.frame.features[:, -5:]).all()


# ------------------------------------------------------------------ frames
T_BASE_LIDAR = Transform.from_yaw(0.3, (1.2, 0.1, 1.8))


def moved_head(t, frame_id, boxes=BOXES, var=VAR, ids=None):
    """``head_msg`` of the same boxes seen from ``frame_id`` (boxes moved by ``t``; the x / y
    variances turned with it)."""
    b, _ = t.apply_boxes(boxes)
    c2, s2 = np.cos(0.3) ** 2, np.sin(0.3) ** 2
    v = var.copy()
    v[:, 0], v[:, 1] = c2 * var[:, 0] + s2 * var[:, 1], s2 * var[:, 0] + c2 * var[:, 1]
    m = detection_array(header(), b, FG, NAMES, ids=ids, variances=v)
    m.header.frame_id = frame_id
    return m, box_variance_array(m.header, v, ids=ids)


def points_models(tmp_path, sp, heads, cloud):
    f = frame_features(heads, None, sp, cloud)
    X = np.vstack([f.features] * 4)
    X[:, -5] = np.arange(len(X))
    X[:, -4] = np.arange(len(X)) % 3
    clf = fit_estimator("linear", "classification", X, (np.arange(len(X)) % 2).astype(float))
    reg = fit_estimator("linear", "regression", X, np.linspace(0, 1, len(X)))
    return MetaModels(*save_pair(tmp_path, "mimo_points", clf, reg, sp.feature_names()),
                      sp.feature_names())


def test_processor_heads_and_cloud_in_other_frames(models, tmp_path):
    """Head 1 and the cloud in base_link with base_link <- lidar known: the outputs of the
    same scene in one frame (head 0's, the output header's); variances turned too."""
    buf = TransformBuffer()
    buf.set_transform("base_link", "lidar", T_BASE_LIDAR, static=True)
    s = MimoSettings()
    h1 = BOXES + [0.3, -0.2, 0, 0.1, 0, 0, 0.05]
    # x / y variances equal: turning them is exact (their covariance is not transported)
    v1 = VAR * [2, 1.6, 1, 1, 1, 1, 1]
    ref = MimoProcessor(s, models).process([head_msg(), head_msg(h1, var=v1, ids=[3, 4, 5])],
                                           [var_msg(), var_msg(v1, ids=[3, 4, 5])])
    mh, mv = moved_head(T_BASE_LIDAR, "base_link", h1, v1, ids=[3, 4, 5])
    proc = MimoProcessor(s, models, transforms=buf)
    out = proc.process([head_msg(), mh], [var_msg(), mv])
    assert out.issues == {}
    np.testing.assert_allclose(out.out.confidence, ref.out.confidence, atol=1e-9)
    np.testing.assert_allclose(out.out.frame.features, ref.out.frame.features, atol=1e-9)
    assert out.out.frame.merged_ids() == ref.out.frame.merged_ids()
    # as if equal (transform_inputs false) the scene differs
    as_if = MimoProcessor(s, models, transform_inputs=False).process([head_msg(), mh],
                                                                     [var_msg(), mv])
    assert "differs from head 0" in as_if.issues["heads"]
    a, b = as_if.out.frame.features, ref.out.frame.features
    assert a.shape != b.shape or not np.allclose(a, b, equal_nan=True)
    # the first head present is the reference: head 0 missing, head 1 (base_link) leads
    only = proc.process([None, mh], [None, mv])
    assert bytes(only.out.detections)[:4] and only.out.frame.heads_used == [1]
    # no transform: the frame is rejected, named
    with pytest.raises(NoTransformError, match="head 1: no transform from 'base_link' to "
                                               "'lidar'") as e:
        MimoProcessor(s, models, transforms=TransformBuffer()).process([head_msg(), mh])
    assert e.value.reason == "no_transform"
    # a quarter turn swaps the x and y variances
    hd, _ = head_detections(head_msg(), var_msg(), s, transform=Transform.from_yaw(np.pi / 2))
    np.testing.assert_allclose(hd.variances[:, [1, 0, 2, 3, 4, 5, 6]], VAR, atol=1e-12)

    # the cloud in base_link (use_points)
    sp = MimoSettings(use_points=True)
    rng = np.random.default_rng(3)
    xyz = np.vstack([rng.uniform(-30, 30, (200, 3))]
                    + [b[:3] + rng.uniform(-0.5, 0.5, (30, 3)) for b in BOXES])
    inten = rng.random(len(xyz))
    heads = [head_msg(), head_msg(h1, ids=[3, 4, 5])]
    pm = points_models(tmp_path, sp, heads, (xyz, inten))
    cloud = create_xyz_cloud(header(), xyz.astype(np.float32), inten.astype(np.float32))
    ref = MimoProcessor(sp, pm).process(heads, None, cloud)
    assert np.isfinite(ref.out.frame.features[:, -5:]).all()
    assert (ref.out.frame.features[:, -5] > 0).all()
    hb = Header(stamp=header().stamp, frame_id="base_link")
    cloud_b = create_xyz_cloud(hb, T_BASE_LIDAR.apply_points(
        xyz.astype(np.float32).astype(np.float64)), inten.astype(np.float32))
    out = MimoProcessor(sp, pm, transforms=buf).process(heads, None, cloud_b)
    assert out.issues == {}
    np.testing.assert_allclose(out.out.frame.features, ref.out.frame.features, atol=1e-5)
    np.testing.assert_allclose(out.out.confidence, ref.out.confidence, atol=1e-6)
    with pytest.raises(NoTransformError, match="input/points: no transform from 'base_link'"):
        MimoProcessor(sp, pm, transforms=TransformBuffer()).process(heads, None, cloud_b)


# --------------------------------------------------------------------------- domain drift
def test_drift_check_flags_another_detectors_scores(tmp_path):
    """Models recording the profile of their training frames: frames like them are quiet,
    heads scoring every box at 40 % of that are out of the domain (ERROR, the score named);
    passthrough then publishes the merged scores as the confidences."""
    from lidar_quality_core.domain_profile import DriftParameters
    from lidar_quality_core.meta_model import training_profile
    from mimo_data import head_frames
    from mimo_ros.pipeline import MimoProcessor, frame_quantities

    s = MimoSettings()
    names = s.feature_names()
    train = [frame_features(heads, variances, s) for _, heads, variances, _ in
             head_frames(n_frames=10, seed=1)]
    X = np.vstack([f.features for f in train])
    prof = training_profile(X, names, {
        "detector score": np.concatenate([f.merge.scores for f in train])})
    (quantities, X0), = frame_quantities(train[0], names)
    assert set(prof["quantities"]) == set(quantities) and X0.shape == (len(train[0].features),
                                                                       len(quantities))
    y = (np.arange(len(X)) % 2).astype(float)
    c, r = save_pair(tmp_path, "mimo", fit_estimator("linear", "classification", X, y),
                     fit_estimator("linear", "regression", X, y), names, domain_profile=prof)
    models = MetaModels(c, r, names)

    def weaker(heads):
        out = []
        for h in heads:
            h = deserialize_message(serialize_message(h), type(h))
            for d in h.detections:
                for res in d.results:
                    res.hypothesis.score *= 0.4
            out.append(h)
        return out

    live = head_frames(n_frames=16, seed=2)
    # weaker scores leave fewer boxes: 8 frames hold the 30 values a score needs
    proc = MimoProcessor(s, models, drift=DriftParameters(drift_window=8))
    for k, (_, heads, variances, _) in enumerate(live[:8]):
        out = proc.process(heads, variances)
        assert out.values["drift.level"] == ("warming up" if k < 7 else "OK"), out.values
        q = sent(out.out.uncertainty)   # output/uncertainty says so too
        assert q.version == q.MESSAGE_VERSION and not q.passthrough
        assert q.drift_window_frames == k + 1
        if k < 7:                       # scoring starts with a full window (8 frames here)
            assert q.drift_level == q.DRIFT_WARMING_UP and np.isnan(q.drift_score)
        else:
            assert q.drift_level == q.DRIFT_OK
            assert q.drift_score == pytest.approx(out.values["drift.score"], abs=5e-4)
    for _, heads, variances, _ in live[8:]:
        out = proc.process(weaker(heads), variances)
    assert out.values["drift.level"] == "ERROR" and "domain_drift" in out.errors, out.values
    assert "detector score" in out.issues["domain_drift"]
    q = sent(out.out.uncertainty)
    assert q.drift_level == q.DRIFT_ERROR and q.drift_score >= 0.5 and not q.passthrough
    assert q.drift_score == pytest.approx(out.values["drift.score"], abs=5e-4)
    assert "detector score" in q.drift_quantities.split(", ")
    assert [c.confidence for c in q.clusters] == out.out.confidence.tolist()

    passthrough = MimoProcessor(s, models, drift=DriftParameters(
        drift_window=8, drift_action="passthrough"))
    for _, heads, variances, _ in live[8:]:
        out = passthrough.process(weaker(heads), variances)
    o = out.out
    np.testing.assert_allclose(o.confidence, o.frame.merge.scores)
    assert np.isnan(o.predicted_iou).all()
    q = sent(o.uncertainty)
    assert q.drift_level == q.DRIFT_ERROR and q.passthrough
    np.testing.assert_allclose([c.confidence for c in q.clusters], o.frame.merge.scores)


def sent(msg):
    """``msg`` as a subscriber gets it: through rclpy's serialization."""
    return deserialize_message(serialize_message(msg), type(msg))
