"""lmd_ros.pipeline: messages -> features (same as compute_features on the same arrays),
exact-mode NMS, invalid boxes, malformed clouds, and the node's frame processor."""
import copy
from dataclasses import replace
import math

import numpy as np
import pytest
from lidar_quality_core import synthetic
from lidar_quality_core.boxes import (arrays_to_detections, detections_to_arrays,
                                      yaw_to_quaternion)
from lidar_quality_core.frame import FrameRejected
from lidar_quality_core.detection_cdr import decode_detection_array
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.nms import rotated_nms
from lidar_quality_core.pointcloud import CloudFormatError, create_cloud, create_xyz_cloud
from lidar_quality_core.transforms import NoTransformError, Transform, TransformBuffer
from rclpy.serialization import deserialize_message, serialize_message
from vision_msgs.msg import Detection3DArray
from lmd_frames import CLASS_NAMES, frame_messages, header, train_models
from lidar_quality_core.lmd.features import ProposalSets, compute_features, feature_names
from lmd_ros.pipeline import (LmdProcessor, LmdSettings, default_model_paths,
                              frame_features, frame_id_mismatch)

H = header(5)


def dets_msg(boxes, scores, labels, ids=None, h=H):
    return arrays_to_detections(h, np.asarray(boxes, float), labels, scores,
                                ids=ids if ids is not None else [f"b{i}" for i in range(len(boxes))])


def hand_frame():
    """Two unit-spaced point blocks with known reflectance, three detections, proposals
    around the first two (and one far away)."""
    g = np.stack(np.meshgrid(np.linspace(-0.9, 0.9, 4), np.linspace(-0.4, 0.4, 3),
                             np.linspace(-0.4, 0.4, 2)), -1).reshape(-1, 3)  # 24 points
    pts = np.concatenate([g + [10, 0, 0], g + [0, 10, 0], [[50, 50, 50]]]).astype(np.float32)
    inten = np.concatenate([np.full(24, 0.5), np.linspace(0, 1, 24), [0.9]]).astype(np.float32)
    boxes = np.array([[10, 0, 0, 2, 1, 1, 0.0], [0, 10, 0, 2, 1.6, 1, 0.3],
                      [-20, 0, 0, 4, 2, 1.5, 1.0]])
    scores = np.array([0.9, 0.7, 0.4])
    labels = ["car", "pedestrian", "cyclist"]
    pboxes = np.concatenate([boxes, boxes[:2] + [0.1, 0, 0, 0, 0, 0, 0.05],
                             boxes[:1] + [0.3, 0.1, 0, 0.2, 0, 0, -0.1],
                             [[40, 40, 0, 2, 2, 2, 0]]])
    pscores = np.array([0.9, 0.7, 0.4, 0.6, 0.5, 0.05, 0.3])
    plabels = ["car", "pedestrian", "cyclist", "car", "pedestrian", "car", "truck"]
    return pts, inten, boxes, scores, labels, pboxes, pscores, plabels


def hand_messages():
    pts, inten, boxes, scores, labels, pboxes, pscores, plabels = hand_frame()
    cloud = create_xyz_cloud(H, pts, inten)
    return (cloud, dets_msg(boxes, scores, labels),
            dets_msg(pboxes, pscores, plabels, ids=[f"p{k}" for k in range(len(pboxes))]))


# ------------------------------------------------------------------ settings
def test_settings_schema_and_validation():
    assert len(LmdSettings().feature_names()) == 90
    assert LmdSettings(proposal_mode="exact").feature_names() == feature_names("exact")
    assert LmdSettings(proposal_mode="none").feature_names() == feature_names("none")
    extra = LmdSettings(class_score_features=True).feature_names()
    assert extra[-4:] == tuple(f"class_score_{c}" for c in CLASS_NAMES)
    LmdSettings().validate()
    for bad, msg in [(dict(proposal_mode="nms"), "proposal_mode"),
                     (dict(iou_threshold=1.0), "iou_threshold"),
                     (dict(iou_threshold=-0.1), "iou_threshold"),
                     (dict(proposal_score_threshold=math.nan), "proposal_score_threshold"),
                     (dict(nms_iou_threshold=1.5), "nms_iou_threshold"),
                     (dict(nms_score_threshold=math.inf), "nms_score_threshold"),
                     (dict(class_names=()), "class_names"),
                     (dict(class_names=("car", "")), "class_names"),
                     (dict(class_names=("car", "car")), "duplicates")]:
        with pytest.raises(ValueError, match=msg):
            LmdSettings(**bad).validate()


def test_default_model_paths(monkeypatch, tmp_path):
    monkeypatch.setenv("LQ_MODELS_DIR", str(tmp_path))
    assert default_model_paths("exact") == (tmp_path / "lmd" / "lmd_exact_classifier.joblib",
                                            tmp_path / "lmd" / "lmd_exact_regressor.joblib")
    with pytest.raises(ValueError):
        default_model_paths("all")


# ------------------------------------------------------------------ features from messages
def test_threshold_mode_equals_compute_features_on_same_arrays():
    pts, inten, boxes, scores, labels, pboxes, pscores, plabels = hand_frame()
    s = LmdSettings(iou_threshold=0.3, proposal_score_threshold=0.1)
    fr = frame_features(*hand_messages(), s)
    want = compute_features(pts, inten, boxes, scores, labels, proposals=(pboxes, pscores),
                            mode="threshold", iou_threshold=0.3, proposal_score_threshold=0.1,
                            class_names=CLASS_NAMES)
    np.testing.assert_allclose(fr.features, want, rtol=1e-12, atol=1e-12)
    assert fr.valid.all() and fr.n_points == 49
    assert [m.id for m in fr.messages] == ["b0", "b1", "b2"]
    f = dict(zip(s.feature_names(), fr.features[1]))
    # known answers: 24 points in box 1 with reflectance linspace(0, 1, 24)
    r = np.linspace(0, 1, 24).astype(np.float32).astype(float)
    assert f["points"] == 24 and f["points_frac"] == pytest.approx(24 / 49)
    assert f["refl_mean"] == pytest.approx(r.mean(), rel=1e-6)
    assert f["refl_std"] == pytest.approx(r.std(), rel=1e-6)
    assert f["class"] == CLASS_NAMES.index("pedestrian") and f["score"] == pytest.approx(0.7)
    assert f["n_proposals"] == 2  # itself + its shifted copy
    # box 0: itself and the shifted copy; the widened copy scores below the threshold
    n_col = s.feature_names().index("n_proposals")
    assert fr.features[:, n_col].tolist() == [2, 2, 1]
    fr0 = frame_features(*hand_messages(), LmdSettings(iou_threshold=0.3))
    assert fr0.features[:, n_col].tolist() == [3, 2, 1]


def test_none_mode_and_class_score_extras():
    pts, inten, boxes, scores, labels, *_ = hand_frame()
    cloud, dets, _ = hand_messages()
    fr = frame_features(cloud, dets, None, LmdSettings(proposal_mode="none"))
    want = compute_features(pts, inten, boxes, scores, labels, mode="none",
                            class_names=CLASS_NAMES)
    np.testing.assert_allclose(fr.features, want, rtol=1e-12, atol=1e-12)
    # per-class hypotheses: absent ones count as 0
    probs = np.array([[0.6, 0.1, 0.2, 0.1], [0.1, 0.0, 0.8, 0.1], [0.3, 0.3, 0.0, 0.4]])
    dets = arrays_to_detections(H, boxes, None, None, ids=[0, 1, 2],
                                class_scores={c: np.where(probs[:, k] > 0, probs[:, k], np.nan)
                                              for k, c in enumerate(CLASS_NAMES)})
    s = LmdSettings(proposal_mode="none", class_score_features=True)
    fr = frame_features(cloud, dets, None, s)
    assert fr.features.shape == (3, 17 + 4)
    np.testing.assert_allclose(fr.features[:, -4:], np.where(probs > 0, probs, 0.0))
    assert fr.features[:, s.feature_names().index("score")].tolist() == [0.6, 0.8, 0.4]


def test_exact_mode_runs_nms_and_keeps_proposal_ids():
    f = synthetic.synthetic_frame(n_points=5000, n_objects=8, n_proposals=120, seed=4)
    cloud, _, props = frame_messages(f, 1)
    # one invalid proposal with the best score: it must neither survive nor break NMS
    props.detections[7].bbox.size.x = float("nan")
    props.detections[7].results[0].hypothesis.score = 2.0
    s = LmdSettings(proposal_mode="exact", nms_iou_threshold=0.1, nms_score_threshold=0.1)
    fr = frame_features(cloud, None, props, s)
    pa = detections_to_arrays(props)
    ok = np.flatnonzero(pa.valid)
    assert len(ok) == len(pa) - 1
    nms = rotated_nms(pa.boxes[ok], pa.scores[ok], 0.1, score_threshold=0.1)
    keep = ok[nms.keep]
    assert [m.id for m in fr.messages] == [f"p{k}" for k in keep.tolist()]
    assert fr.detections.ids == [f"p{k}" for k in keep.tolist()]
    assert all(m is props.detections[k] for m, k in zip(fr.messages, keep.tolist()))
    sup = np.full(len(pa), -1)
    sup[ok[nms.suppressed_by >= 0]] = ok[nms.suppressed_by[nms.suppressed_by >= 0]]
    want = compute_features(f.points, f.intensity, pa.boxes[keep], pa.scores[keep],
                            [pa.labels[k] for k in keep], proposals=(pa.boxes, pa.scores),
                            mode="exact", preimage=ProposalSets.from_nms(sup, keep),
                            class_names=CLASS_NAMES)
    np.testing.assert_allclose(fr.features, want, rtol=1e-12, atol=1e-12)
    n_prop = fr.features[:, s.feature_names().index("n_proposals")]
    assert n_prop.sum() == np.count_nonzero(sup >= 0)  # every NMS input in exactly one set
    assert len(keep) and (pa.scores[keep] >= 0.1).all()


def test_invalid_boxes_get_nan_rows_and_leave_the_others_alone():
    pts, inten, boxes, scores, labels, pboxes, pscores, plabels = hand_frame()
    cloud, _, props = hand_messages()
    bad = np.array([[1, 1, 0, 2, 1, 1, 0], [2, 2, 0, 0.0, 1, 1, 0], [3, 3, 0, 2, 1, 1, 0]], float)
    bad[0, 1] = np.nan
    all_boxes = np.concatenate([boxes[:1], bad, boxes[1:]])
    dets = dets_msg(all_boxes, np.r_[scores[:1], 0.5, 0.5, 0.5, scores[1:]],
                    labels[:1] + ["car", "car", "bus"] + labels[1:])
    dets.detections.insert(2, type(dets.detections[0])(id="empty"))  # no hypothesis
    fr = frame_features(cloud, dets, props, LmdSettings())
    assert [m.id for m in fr.messages] == ["b0", "b1", "empty", "b2", "b3", "b4", "b5"]
    assert fr.valid.tolist() == [True, False, False, False, False, True, True]
    assert np.isnan(fr.features[~fr.valid]).all()
    r = fr.detections.reasons
    assert "non-finite centre" in r[1] and "no hypothesis" in r[2] and "size <= 0" in r[3]
    assert r[4] == "unknown class 'bus'"
    good = frame_features(*hand_messages(), LmdSettings()).features
    np.testing.assert_allclose(fr.features[fr.valid], good, rtol=1e-12)


def test_empty_detections():
    cloud, _, props = hand_messages()
    fr = frame_features(cloud, dets_msg(np.zeros((0, 7)), [], []), props, LmdSettings())
    assert fr.features.shape == (0, 90) and fr.messages == [] and fr.valid.shape == (0,)


def test_malformed_clouds_raise_cloud_format_error():
    cloud, dets, props = hand_messages()
    cloud.data = cloud.data[:50]
    with pytest.raises(CloudFormatError, match="truncated"):
        frame_features(cloud, dets, props, LmdSettings())
    no_intensity = create_xyz_cloud(H, np.zeros((4, 3), np.float32))
    with pytest.raises(CloudFormatError, match="intensity"):
        frame_features(no_intensity, dets, props, LmdSettings())
    no_z = create_cloud(H, {"x": np.zeros(4, np.float32), "y": np.zeros(4, np.float32),
                            "intensity": np.zeros(4, np.float32)})
    with pytest.raises(CloudFormatError, match="'z'"):
        frame_features(no_z, dets, props, LmdSettings())
    with pytest.raises(ValueError, match="proposals"):
        frame_features(hand_messages()[0], dets, None, LmdSettings())


def test_nan_points_are_not_counted():
    pts, inten, *_ = hand_frame()
    pts = pts.copy()
    pts[0, 2] = np.nan
    inten = inten.copy()
    inten[30] = np.nan
    _, dets, props = hand_messages()
    fr = frame_features(create_xyz_cloud(H, pts, inten), dets, props, LmdSettings())
    assert fr.n_points == 47
    names = LmdSettings().feature_names()
    assert fr.features[0, names.index("points")] == 23
    assert fr.features[1, names.index("points")] == 23


def test_frame_id_mismatch():
    cloud, dets, props = hand_messages()
    assert frame_id_mismatch(cloud, dets, props) is None
    dets.header = header(5, "base_link")
    msg = frame_id_mismatch(cloud, dets, None)
    assert "input/points 'lidar_top'" in msg and "input/detections 'base_link'" in msg


# ------------------------------------------------------------------ processor
@pytest.fixture(scope="module")
def threshold_models(tmp_path_factory):
    s = LmdSettings()
    return s, MetaModels(*train_models(tmp_path_factory.mktemp("lmd"), s), s.feature_names())


def test_processor_outputs_match_models_on_frame_features(threshold_models):
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=12, n_proposals=120, seed=9)
    cloud, dets, props = frame_messages(f, 3)
    ids = [d.id for d in dets.detections]
    ref = frame_features(*frame_messages(f, 3), s)
    conf, iou = models.predict(ref.features)
    out = LmdProcessor(s, models).process(cloud, dets, props, markers=True)
    np.testing.assert_array_equal(out.confidence, conf)
    np.testing.assert_array_equal(out.predicted_iou, iou)
    assert [d.id for d in out.detections.detections] == ids and out.kept.all()
    assert out.detections.header == dets.header and out.quality.header == dets.header
    tops = [max(r.hypothesis.score for r in d.results) for d in out.detections.detections]
    np.testing.assert_allclose(tops, conf)
    q = out.quality
    assert q.confidence_model_id == models.confidence_model_id != ""
    assert q.iou_model_id == models.iou_model_id
    assert [e.detection_index for e in q.detections] == list(range(len(ids)))
    assert [e.detection_id for e in q.detections] == ids
    np.testing.assert_allclose([e.original_score for e in q.detections], ref.detections.scores)
    np.testing.assert_allclose([e.confidence for e in q.detections], conf)
    np.testing.assert_allclose([e.predicted_iou for e in q.detections], iou)
    texts = [m.text for m in out.markers.markers if m.text]
    assert texts[0] == f"{ref.detections.labels[0]} c={conf[0]:.2f} iou={iou[0]:.2f}"
    assert len(texts) == len(ids) and out.issues == {}
    # min_confidence: the only way a detection disappears; the quality array keeps all
    thr = float(np.median(conf))
    out2 = LmdProcessor(s, models, min_confidence=thr).process(*frame_messages(f, 3))
    assert [d.id for d in out2.detections.detections] == [i for i, c in zip(ids, conf) if c >= thr]
    assert len(out2.quality.detections) == len(ids)


def test_processor_flags_invalid_boxes(threshold_models):
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=6, n_proposals=60, seed=2)
    cloud, dets, props = frame_messages(f, 3)
    dets.detections[1].bbox.size.y = 0.0
    dets.detections[2].results[0].hypothesis.class_id = "tram"
    dets.header = header(3, "odom")
    out = LmdProcessor(s, models, min_confidence=0.01, transform_inputs=False).process(
        cloud, dets, props)
    assert np.isnan(out.confidence[1:3]).all() and np.isfinite(out.confidence[3:]).all()
    assert "2 invalid" in out.issues["detections"] and "unknown class 'tram'" in out.issues["detections"]
    assert "frame_id" in out.issues["frame_id"]
    assert [d.id for d in out.detections.detections] == [
        d for k, d in enumerate(out.frame.detections.ids) if k not in (1, 2)
        and out.confidence[k] >= 0.01]
    kept_all = LmdProcessor(s, models).process(*frame_messages(f, 3)[:2], props)
    assert len(kept_all.detections.detections) == len(dets.detections)


def test_processor_refuses_mismatched_models(threshold_models):
    _, models = threshold_models
    with pytest.raises(ValueError, match="feature schema"):
        LmdProcessor(LmdSettings(proposal_mode="none"), models)
    with pytest.raises(ValueError, match="min_confidence"):
        LmdProcessor(LmdSettings(), models, min_confidence=1.5)


def decoded(msg):
    return decode_detection_array(serialize_message(msg))


@pytest.mark.parametrize("mode", ["threshold", "exact", "none"])
def test_decoded_input_gives_the_same_features(mode):
    f = synthetic.synthetic_frame(n_points=5000, n_objects=8, n_proposals=120, seed=5)
    cloud, dets, props = frame_messages(f, 1)
    dets.detections[2].bbox.size.x = 0.0
    s = LmdSettings(proposal_mode=mode)
    a = frame_features(cloud, dets, props if mode != "none" else None, s)
    b = frame_features(cloud, decoded(dets), decoded(props) if mode != "none" else None, s)
    np.testing.assert_array_equal(a.features, b.features)
    assert a.detections.ids == b.detections.ids and b.messages is None
    np.testing.assert_array_equal(a.rows, b.rows)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.header == b.header


@pytest.mark.parametrize("mode, min_conf", [("threshold", 0.0), ("threshold", 0.6),
                                            ("exact", 0.0), ("exact", 0.6)])
def test_processor_bytes_output_equals_message_output(mode, min_conf, tmp_path):
    s = LmdSettings(proposal_mode=mode)
    models = MetaModels(*train_models(tmp_path, s, n_frames=3), s.feature_names())
    proc = LmdProcessor(s, models, min_confidence=min_conf)
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=12, n_proposals=120, seed=8)
    cloud, dets, props = frame_messages(f, 2)
    dets.detections[1].results[0].hypothesis.class_id = "tram"  # NaN confidence
    if mode == "exact":
        dets = None
    want = proc.process(cloud, dets, props)
    cloud, dets, props = frame_messages(f, 2)
    dets.detections[1].results[0].hypothesis.class_id = "tram"
    got = proc.process(cloud, None if mode == "exact" else decoded(dets), decoded(props))
    assert isinstance(got.detections, bytes)
    # the node's output/quality as bytes: the same message
    as_bytes = LmdProcessor(s, models, min_confidence=min_conf, serialized_quality=True)
    cloud, dets, props = frame_messages(f, 2)
    dets.detections[1].results[0].hypothesis.class_id = "tram"
    raw = as_bytes.process(cloud, None if mode == "exact" else decoded(dets),
                           decoded(props)).quality
    assert isinstance(raw, bytes)   # NaN != NaN: field by field
    a, b = sent_quality(raw), sent_quality(got)
    assert (a.header, a.confidence_model_id, a.iou_model_id, a.version, a.drift_level) == (
        b.header, b.confidence_model_id, b.iou_model_id, b.version, b.drift_level)
    for field in ("detection_index", "detection_id", "class_id", "original_score",
                  "confidence", "predicted_iou"):
        np.testing.assert_array_equal([getattr(e, field) for e in a.detections],
                                      [getattr(e, field) for e in b.detections])
    out = deserialize_message(got.detections, Detection3DArray)
    ref = want.detections
    assert out.header == ref.header and len(out.detections) == len(ref.detections)
    assert 0 < len(out.detections) and (min_conf == 0) == (len(out.detections) == len(want.kept))
    for a, b in zip(out.detections, ref.detections):
        assert a.id == b.id and a.bbox == b.bbox and a.header == b.header
        assert [r.pose for r in a.results] == [r.pose for r in b.results]
        np.testing.assert_array_equal([r.hypothesis.score for r in a.results],
                                      [r.hypothesis.score for r in b.results])
    assert got.quality.header == want.quality.header
    for field in ("detection_id", "class_id", "original_score", "confidence", "predicted_iou"):
        np.testing.assert_array_equal([getattr(e, field) for e in got.quality.detections],
                                      [getattr(e, field) for e in want.quality.detections])
    assert np.isnan(got.confidence).sum() == (mode == "threshold")  # the "tram" detection


# ------------------------------------------------------------------ scores, roll / pitch
def _with_hyp_score(msg, i, score):
    msg.detections[i].results[0].hypothesis.score = float(score)
    return msg


@pytest.mark.parametrize("bad", [1.7, -0.3, 1e6])
def test_detection_scores_outside_unit_range_are_not_scored(bad):
    """A detection scoring 1.7 / -0.3 / 1e6 (logits, a bug) was scored like a probability
    without a word; now it is invalid (NaN features), reported, and the others unchanged."""
    cloud, dets, props = hand_messages()
    fr = frame_features(cloud, _with_hyp_score(dets, 1, bad), props, LmdSettings())
    assert fr.valid.tolist() == [True, False, True]
    assert np.isnan(fr.features[1]).all()
    assert fr.detections.reasons[1] == f"score {bad:.6g} outside [0, 1]"
    assert fr.issues["scores"].startswith(
        f"input/detections: 1 of 3 boxes score outside [0, 1] ({bad:.6g} .. {bad:.6g}; "
        "the meta models take probabilities): not scored")
    good = frame_features(*hand_messages(), LmdSettings())
    np.testing.assert_array_equal(fr.features[[0, 2]], good.features[[0, 2]])
    assert good.issues == {}


@pytest.mark.parametrize("mode", ["threshold", "exact"])
def test_proposal_scores_outside_unit_range_are_left_out(mode):
    """A proposal scoring 1e6 entered the proposal statistics (threshold) or won NMS
    (exact); now it belongs to no set, as an invalid proposal, and is reported."""
    pts, inten, boxes, scores, labels, pboxes, pscores, plabels = hand_frame()
    cloud, dets, props = hand_messages()
    s = LmdSettings(proposal_mode=mode)
    fr = frame_features(cloud, None if mode == "exact" else dets,
                        _with_hyp_score(props, 3, 1e6), s)
    keep = np.arange(len(pboxes)) != 3
    want = frame_features(cloud, None if mode == "exact" else dets,
                          dets_msg(pboxes[keep], pscores[keep],
                                   [c for c, k in zip(plabels, keep) if k],
                                   ids=[f"p{k}" for k in np.flatnonzero(keep)]), s)
    np.testing.assert_array_equal(fr.features, want.features)
    assert fr.detections.ids == want.detections.ids and "p3" not in fr.detections.ids
    effect = ("left out of NMS and of every proposal set" if mode == "exact"
              else "left out of every proposal set")
    assert fr.issues == {"scores": "input/proposals: 1 of 7 boxes score outside [0, 1] "
                                   "(1e+06 .. 1e+06; the meta models take probabilities): "
                                   + effect}


def _rpy_quaternion(roll, pitch, yaw):
    """x, y, z, w of R = Rz(yaw) Ry(pitch) Rx(roll) (written out, not the module's)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def test_tilted_boxes_are_kept_and_reported():
    """A box with 30 deg roll lost its roll without a word; it is still read as upright
    with its yaw (the same features), and now reported."""
    cloud, dets, props = hand_messages()
    o = dets.detections[1].bbox.center.orientation
    o.x, o.y, o.z, o.w = _rpy_quaternion(math.radians(30), 0.0, 0.3)
    o = props.detections[0].bbox.center.orientation
    o.x, o.y, o.z, o.w = _rpy_quaternion(0.0, math.radians(-2.5), 0.0)
    fr = frame_features(cloud, dets, props, LmdSettings())
    assert fr.valid.all()
    upright = frame_features(*hand_messages(), LmdSettings())
    np.testing.assert_allclose(fr.features, upright.features, rtol=1e-12, atol=1e-12)
    assert fr.issues == {"roll_pitch": (
        "input/proposals: 1 of 7 proposals have roll/pitch up to 2.5 deg: only yaw is used "
        "(boxes are read as upright); input/detections: 1 of 3 detections have roll/pitch up "
        "to 30.0 deg: only yaw is used (boxes are read as upright)")}
    # the same from serialized input
    dec = frame_features(cloud, decoded(dets), decoded(props), LmdSettings())
    assert dec.issues == fr.issues


def test_processor_reports_scores_and_tilt(threshold_models):
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=6, n_proposals=60, seed=2)
    cloud, dets, props = frame_messages(f, 3)
    _with_hyp_score(dets, 0, 1.7)
    o = dets.detections[2].bbox.center.orientation
    o.x, o.y, o.z, o.w = _rpy_quaternion(math.radians(30), 0.0, 0.0)
    out = LmdProcessor(s, models).process(cloud, dets, props)
    assert set(out.issues) == {"scores", "roll_pitch", "detections"}
    assert "score 1.7 outside [0, 1]" in out.issues["detections"]
    assert np.isnan(out.confidence[0]) and np.isfinite(out.confidence[1:]).all()
    assert "up to 30.0 deg" in out.issues["roll_pitch"]


# ------------------------------------------------------------------ frames
def in_frame(msg, t: Transform, frame_id: str):
    """A copy of Detection3DArray ``msg`` with every box moved by ``t`` (upright boxes:
    centre by ``t``, yaw plus ``t``'s yaw) and ``frame_id`` in its header."""
    out = copy.deepcopy(msg)
    out.header.frame_id = frame_id
    a = detections_to_arrays(msg)
    moved, _ = t.apply_boxes(a.boxes)
    quat = yaw_to_quaternion(moved[:, 6])
    for d, b, q in zip(out.detections, moved, quat):
        p, o = d.bbox.center.position, d.bbox.center.orientation
        p.x, p.y, p.z = b[:3].tolist()
        o.x, o.y, o.z, o.w = q.tolist()
    return out


#: base_link <- lidar_top: a roof lidar 1.2 m ahead, 1.8 m up, turned by 0.3 rad
T_BASE_LIDAR = Transform.from_yaw(0.3, (1.2, 0.1, 1.8))


def static_buffer(t=T_BASE_LIDAR):
    buf = TransformBuffer()
    buf.set_transform("base_link", "lidar_top", t, static=True)
    return buf


def boxes_of(msg):
    return np.array([[d.bbox.center.position.x, d.bbox.center.position.y,
                      d.bbox.center.position.z, d.bbox.size.x, d.bbox.size.y, d.bbox.size.z,
                      d.bbox.center.orientation.z] for d in msg.detections])


@pytest.mark.parametrize("decoded", [False, True])
def test_processor_inputs_in_another_frame_give_the_same_outputs(threshold_models, decoded):
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=12, n_proposals=120, seed=21)
    ref = LmdProcessor(s, models).process(*frame_messages(f, 3))
    cloud, dets, props = frame_messages(f, 3)
    dets_b = in_frame(dets, T_BASE_LIDAR, "base_link")
    props_b = in_frame(props, T_BASE_LIDAR, "base_link")
    sent = boxes_of(dets_b)
    if decoded:  # as the node takes them: bytes decoded by detection_cdr
        dets_b, props_b = (decode_detection_array(serialize_message(m))
                           for m in (dets_b, props_b))
    # the scene really differs in base_link: computed as if equal, confidences move
    as_if = LmdProcessor(s, models, transform_inputs=False).process(
        cloud, *(copy.deepcopy(m) if not decoded else m for m in (dets_b, props_b)))
    assert "frame_id mismatch" in as_if.issues["frame_id"]
    assert np.nanmax(np.abs(as_if.confidence - ref.confidence)) > 0.05
    fresh = [copy.deepcopy(m) if not decoded else m for m in (dets_b, props_b)]
    proc = LmdProcessor(s, models, transforms=static_buffer())
    out = proc.process(cloud, dets_b, props_b, markers=True)
    np.testing.assert_allclose(out.confidence, ref.confidence, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.predicted_iou, ref.predicted_iou, rtol=0, atol=1e-9)
    assert out.issues == {} and ref.confidence.min() < 0.5 < ref.confidence.max()
    # outputs keep the input detections' header, boxes, order and ids
    got = deserialize_message(out.detections, Detection3DArray) if decoded else out.detections
    assert got.header.frame_id == "base_link" and out.quality.header.frame_id == "base_link"
    np.testing.assert_array_equal(boxes_of(got), sent)
    assert [d.id for d in got.detections] == [d.id for d in dets.detections]
    # markers draw the boxes where they were computed: in the cloud's frame
    assert {m.header.frame_id for m in out.markers.markers} == {"lidar_top"}
    # a lookup callable works as well as the buffer
    out2 = LmdProcessor(s, models, transforms=static_buffer().lookup).process(cloud, *fresh)
    np.testing.assert_array_equal(out2.confidence, out.confidence)


def test_processor_chains_timestamped_transforms(threshold_models):
    """Detections in ``odom`` while the vehicle moves: odom <- base_link from /tf samples
    (interpolated at the detections' stamp), base_link <- lidar_top static."""
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=10, n_proposals=100, seed=22)
    ref = LmdProcessor(s, models).process(*frame_messages(f, 3))
    buf = static_buffer()
    for k in range(5):  # 2.8 .. 3.2 s, driving and turning
        buf.set_transform("odom", "base_link", Transform.from_yaw(0.1 * k, (5.0 * k, 1.0, 0)),
                          2_800_000_000 + 100_000_000 * k)
    t_odom_lidar = Transform.from_yaw(0.2, (10.0, 1.0, 0)) * T_BASE_LIDAR  # at k = 2 (3.0 s)
    cloud, dets, props = frame_messages(f, 3)
    out = LmdProcessor(s, models, transforms=buf).process(
        cloud, in_frame(dets, t_odom_lidar, "odom"), in_frame(props, t_odom_lidar, "odom"))
    np.testing.assert_allclose(out.confidence, ref.confidence, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.predicted_iou, ref.predicted_iou, rtol=0, atol=1e-9)


def test_processor_missing_transform_rejects_the_frame(threshold_models):
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=5_000, n_objects=4, n_proposals=40, seed=23)
    cloud, dets, props = frame_messages(f, 3)
    dets_b = in_frame(dets, T_BASE_LIDAR, "base_link")
    for transforms in (None, TransformBuffer()):
        with pytest.raises(NoTransformError) as e:
            LmdProcessor(s, models, transforms=transforms).process(cloud, dets_b, props)
        assert isinstance(e.value, FrameRejected)
        assert e.value.reason == "no_transform" and e.value.cause == "no_transform"
        text = str(e.value)
        assert "input/detections" in text and "'base_link'" in text and "'lidar_top'" in text
        assert "transform_inputs: false" in text
    with pytest.raises(NoTransformError, match=r"at stamp 3\.000000000 s: frame 'base_link' "
                                               r"and frame 'lidar_top' are unknown"):
        LmdProcessor(s, models, transforms=TransformBuffer()).process(cloud, dets_b, props)
    # exact mode: the proposals are what is moved
    out = LmdProcessor(s, models, transforms=static_buffer()).process(
        cloud, dets, in_frame(props, T_BASE_LIDAR, "base_link"))
    assert out.issues == {}


def test_processor_tilting_transform_is_reported(threshold_models):
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=5_000, n_objects=4, n_proposals=40, seed=24)
    cloud, dets, props = frame_messages(f, 3)
    tilt = Transform([0, 0, 1.8], [0.0, np.sin(0.05), 0.0, np.cos(0.05)])  # 5.7 deg pitch
    buf = static_buffer(tilt)
    out = LmdProcessor(s, models, transforms=buf).process(
        cloud, in_frame(dets, T_BASE_LIDAR, "base_link"), props)
    assert "input/detections: the transform tilts by 5.7 deg" in out.issues["transform"]
    # an empty frame_id cannot be looked up: taken as the cloud's, and said so
    dets.header = header(3, "")
    out = LmdProcessor(s, models, transforms=buf).process(cloud, dets, props)
    assert "empty frame_id" in out.issues["frame_id"]


def test_intensity_scale_auto_gives_the_same_outputs_in_both_scales(threshold_models):
    """A driver's 0..255 intensity: before, the same scan scaled by 255 moved confidences
    (up to 0.40 on real scans) and nothing said so; auto reads both as [0, 1]."""
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=12, n_proposals=120, seed=9)
    assert 0.0 <= f.intensity.min() and f.intensity.max() <= 1.0
    cloud, dets, props = frame_messages(f, 3)
    cloud255 = frame_messages(replace(f, intensity=(f.intensity * 255).astype(np.float32)), 3)[0]
    ref_proc = LmdProcessor(s, models)
    ref = ref_proc.process(cloud, copy.deepcopy(dets), copy.deepcopy(props))
    proc = LmdProcessor(s, models)
    out = proc.process(cloud255, copy.deepcopy(dets), copy.deepcopy(props))
    np.testing.assert_allclose(out.confidence, ref.confidence, atol=1e-5)
    np.testing.assert_allclose(out.predicted_iou, ref.predicted_iou, atol=1e-5)
    assert out.values["intensity_scale"] == "byte" and "0..255" in out.notes[0]
    assert ref.values["intensity_scale"] == "unit" and "[0, 1]" in ref.notes[0]
    assert proc.process(cloud255, copy.deepcopy(dets), copy.deepcopy(props)).notes == []
    # the same scan read as given ('unit'): the reflectance features are 255x off
    raw = LmdProcessor(replace(s, intensity_scale="unit"), models).process(
        cloud255, copy.deepcopy(dets), copy.deepcopy(props))
    assert np.nanmax(np.abs(raw.confidence - ref.confidence)) > 1e-3
    rounded = replace(f, intensity=np.round(f.intensity * 255).astype(np.float32))  # drivers
    r = LmdProcessor(s, models).process(frame_messages(rounded, 3)[0], copy.deepcopy(dets),
                                        copy.deepcopy(props))
    assert np.nanmax(np.abs(r.confidence - ref.confidence)) < 0.05


def test_padding_points_are_left_out_and_counted(threshold_models):
    """An organized cloud's (0, 0, 0) no-return pixels are no points: before, they counted
    in |X| (points_frac) and fell into any box around the sensor."""
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=12, n_proposals=120, seed=9)
    cloud, dets, props = frame_messages(f, 3)
    pts = np.concatenate([f.points, np.zeros((5000, 3)), [[np.nan, 0, 0]]]).astype(np.float32)
    inten = np.concatenate([f.intensity, np.full(5000, 0.3), [0.1]]).astype(np.float32)
    padded = create_xyz_cloud(cloud.header, pts, inten)
    ref = LmdProcessor(s, models).process(cloud, copy.deepcopy(dets), copy.deepcopy(props))
    out = LmdProcessor(s, models).process(padded, copy.deepcopy(dets), copy.deepcopy(props))
    np.testing.assert_array_equal(out.frame.features, ref.frame.features)
    assert out.counts["points.in"] == len(pts) and out.counts["points.padding"] == 5000
    # invalid as LMS counts it: every point left out (NaN or padding), of which padding
    assert out.counts["points.invalid"] == 5001 and ref.counts["points.padding"] == 0
    # said once per stream (a log line: padding is right, not a fault), never for none
    proc = LmdProcessor(s, models)
    first = proc.process(padded, copy.deepcopy(dets), copy.deepcopy(props))
    assert any("5000 of 25001" in n and "points.padding" in n for n in first.notes)
    assert not any("padding" in n for n in proc.process(
        padded, copy.deepcopy(dets), copy.deepcopy(props)).notes)
    assert not any("padding" in n for n in ref.notes)


def test_padding_in_a_box_around_the_sensor_is_still_left_out(threshold_models):
    """The cloud is read as a view, its padding only counted: a box that contains the
    sensor's origin (where the padding is) gets the padding blanked in a copy, so that the
    box counts only its real points, as before the view."""
    s, models = threshold_models
    f = synthetic.synthetic_frame(n_points=20_000, n_objects=12, n_proposals=120, seed=9)
    f.detections[0, :6] = [0.5, 0.0, 0.0, 4.0, 2.0, 2.0]  # around the origin
    f.proposals[0, :6] = [0.4, 0.1, 0.0, 4.0, 2.0, 2.0]
    cloud, dets, props = frame_messages(f, 3)
    pts = np.concatenate([f.points, np.zeros((700, 3))]).astype(np.float32)
    inten = np.concatenate([f.intensity, np.full(700, 0.3)]).astype(np.float32)
    padded = create_xyz_cloud(cloud.header, pts, inten)
    ref = LmdProcessor(s, models).process(cloud, copy.deepcopy(dets), copy.deepcopy(props))
    out = LmdProcessor(s, models).process(padded, copy.deepcopy(dets), copy.deepcopy(props))
    np.testing.assert_array_equal(out.frame.features, ref.frame.features)
    assert out.counts["points.padding"] == 700


def test_the_cloud_view_gives_the_features_of_the_blanked_copy(threshold_models):
    """lmd reads the cloud without copying it (a read-only view into the message, the
    padding counted, not blanked): the features equal, bit for bit, those of the copy
    with its padding blanked that it read before, with and without padding and NaN."""
    from lidar_quality_core.pointcloud import (blank_padding, padding_counts, xyz_intensity,
                                               xyz_intensity_view)

    s, _ = threshold_models
    f = synthetic.synthetic_frame(n_points=30_000, n_objects=12, n_proposals=120, seed=4)
    cloud, dets, props = frame_messages(f, 3)
    pts = f.points.astype(np.float32)
    pts[::97] = 0.0   # padding
    pts[5::101, 1] = np.nan
    inten = f.intensity.astype(np.float32)
    inten[7::89] = np.inf
    for msg in (cloud, create_xyz_cloud(cloud.header, pts, inten)):
        view, vi = xyz_intensity_view(msg)
        assert not view.flags.writeable and not view.flags.owndata  # no copy of the cloud
        xyz, xi = xyz_intensity(msg)
        np.testing.assert_array_equal(view, xyz)
        counts = padding_counts(view, vi)
        assert counts == blank_padding(xyz, xi)
        arrays = detections_to_arrays(dets)
        parr = detections_to_arrays(props)
        kw = dict(proposals=(parr.boxes, parr.scores), mode="threshold",
                  class_names=s.class_names, iou_threshold=s.iou_threshold,
                  proposal_score_threshold=s.proposal_score_threshold)
        want = compute_features(xyz, xi, arrays.boxes, arrays.scores, arrays.labels, **kw)
        got = frame_features(msg, dets, props, s).features
        np.testing.assert_array_equal(got, want)


# --------------------------------------------------------------------------- domain drift
def shifted(f, factor):
    """Frame ``f`` as another detector would score it: every score times ``factor``."""
    return replace(f, det_scores=f.det_scores * factor, prop_scores=f.prop_scores * factor)


def sent_quality(out):
    """``out.quality`` (or those bytes) as a subscriber gets it: through rclpy's
    serialization, or the bytes as they are published."""
    from lidar_quality_msgs.msg import DetectionQualityArray

    q = out if isinstance(out, bytes) else out.quality
    return deserialize_message(q if isinstance(q, bytes) else serialize_message(q),
                               DetectionQualityArray)


def assert_drift_fields(q, out, level):
    """The quality message ``q`` carries the frame's drift verdict as /diagnostics has it."""
    assert q.version == q.MESSAGE_VERSION == 1
    assert q.drift_level == level
    v = out.values
    if level in (q.DRIFT_OK, q.DRIFT_WARN, q.DRIFT_ERROR):
        assert q.drift_level - q.DRIFT_OK == ["OK", "WARN", "ERROR"].index(v["drift.level"])
        assert q.drift_score == pytest.approx(v["drift.score"], abs=5e-4)
    else:
        assert math.isnan(q.drift_score) and "drift.score" not in v
        if level == q.DRIFT_WARMING_UP:
            assert v["drift.level"] == "warming up"
    assert q.drift_window_frames == v.get("drift.window_frames", 0)
    assert q.drift_quantities == v.get("drift.quantities", "")


def test_drift_check_flags_frames_unlike_the_training_data(tmp_path):
    """/diagnostics and every frame's output/quality say how far the inputs are from the
    models' training data: warming up, then OK in the training domain; ERROR, the detector
    score named, for another detector's scores (x 0.3); with passthrough the message says
    its confidences are the detector's."""
    from lidar_quality_core.domain_profile import DriftParameters

    settings = LmdSettings(proposal_mode="none")
    models = MetaModels(*train_models(tmp_path, settings, n_frames=8, profile=True),
                        settings.feature_names())
    assert models.domain_profile is not None
    frames = [synthetic.synthetic_frame(n_points=20_000, n_objects=15, n_proposals=150,
                                        seed=700 + k) for k in range(8)]
    proc = LmdProcessor(settings, models, drift=DriftParameters(drift_window=4))
    for k, f in enumerate(frames[:4]):                    # the training domain: quiet
        cloud, dets, _ = frame_messages(f, k + 1)
        out = proc.process(cloud, dets, None)
        assert out.values["drift.level"] == ("warming up" if k < 3 else "OK"), out.values
        assert "domain_drift" not in out.issues
        q = sent_quality(out)
        # scoring starts with a full window (4 frames here, 10 by default)
        assert_drift_fields(q, out, q.DRIFT_WARMING_UP if k < 3 else q.DRIFT_OK)
        assert q.drift_window_frames == k + 1 and not q.passthrough
        assert [d.confidence for d in q.detections] == out.confidence.tolist()
    levels = []
    for k, f in enumerate(frames[4:]):                    # another detector's scores
        cloud, dets, _ = frame_messages(shifted(f, 0.3), k + 5)
        out = proc.process(cloud, dets, None)
        levels.append(out.values["drift.level"])
        q = sent_quality(out)
        assert_drift_fields(q, out, q.DRIFT_OK + ["OK", "WARN", "ERROR"].index(levels[-1]))
    assert levels[-1] == "ERROR" and "domain_drift" in out.errors
    assert "detector score" in out.issues["domain_drift"]
    assert "another detector?" in out.issues["domain_drift"]
    assert np.isfinite(out.confidence[out.frame.valid]).all()   # flag: annotated as always
    assert q.drift_level == q.DRIFT_ERROR and q.drift_score >= 0.5 and not q.passthrough
    assert "detector score" in q.drift_quantities.split(", ")
    assert q.drift_window_frames == 4

    passthrough = LmdProcessor(settings, models, drift=DriftParameters(
        drift_window=2, drift_action="passthrough"), serialized_quality=True)  # as the node
    for k, f in enumerate(frames[4:]):
        cloud, dets, _ = frame_messages(shifted(f, 0.3), k + 5)
        out = passthrough.process(cloud, dets, None)
    v = out.frame.valid
    assert out.values["drift.level"] == "ERROR"
    assert np.array_equal(out.confidence[v], out.frame.detections.scores[v])
    assert np.isnan(out.predicted_iou).all()
    q = sent_quality(out)
    assert_drift_fields(q, out, q.DRIFT_ERROR)
    assert q.passthrough
    conf = np.array([d.confidence for d in q.detections])
    assert np.array_equal(conf[v], [d.original_score for d, ok in zip(q.detections, v) if ok])


def test_models_without_a_profile_say_the_drift_check_is_off(tmp_path):
    settings = LmdSettings(proposal_mode="none")
    models = MetaModels(*train_models(tmp_path, settings, n_frames=2),
                        settings.feature_names())
    assert models.domain_profile is None
    f = synthetic.synthetic_frame(n_points=5_000, n_objects=5, n_proposals=40, seed=3)
    cloud, dets, _ = frame_messages(f, 1)
    out = LmdProcessor(settings, models).process(cloud, dets, None)
    assert out.values["drift"].startswith("off: the models record no training-data")
    assert "domain_drift" not in out.issues
    q = sent_quality(out)
    assert_drift_fields(q, out, q.DRIFT_OFF)
    assert q.drift_window_frames == 0 and not q.passthrough
