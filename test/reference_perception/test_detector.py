"""Tests of reference_perception.detector: residual coding, training labels, the trained
reference detector (acceptance: an isolated car at 10 m; NMS bookkeeping) and a small
train -> save -> load -> detect round trip."""
import json
from itertools import islice
from types import SimpleNamespace

import numpy as np
import pytest
from car_scene import car_scene
from lidar_quality_core.iou import iou_3d_pairs, iou_bev, iou_bev_pairs
from lidar_sim.frames import split_frames
from reference_perception.detector import (FG_CLASS_IDS, PROB_NAMES, DetectorConfig,
                                           ReferenceDetector, decode_residuals,
                                           default_model_dir, encode_residuals,
                                           proposal_targets, train_detector)
from reference_perception.proposals import compute_proposals

MODEL_DIR = default_model_dir()
needs_models = pytest.mark.skipif(
    not (MODEL_DIR / "detector.json").is_file(),
    reason=f"no trained detector in {MODEL_DIR} (python -m reference_perception.detector train)")


# ------------------------------------------------------------------ no models needed
def test_residual_round_trip():
    rng = np.random.default_rng(0)
    n = 500
    b = np.c_[rng.uniform(-60, 60, (n, 2)), rng.uniform(-1.5, 0, n), rng.uniform(0.1, 6, (n, 3)),
              rng.uniform(-np.pi / 2, np.pi / 2, n)]
    g = b + np.c_[rng.normal(0, 1, (n, 3)), rng.uniform(0, 2, (n, 3)), rng.normal(0, 1, n)]
    r = decode_residuals(b, encode_residuals(b, g))
    # the same rectangle (up to l / w swap and heading): full overlap
    np.testing.assert_allclose(iou_3d_pairs(r, g), 1.0, atol=1e-9)
    assert np.all(np.abs(encode_residuals(b, g)[:, 6]) <= np.pi / 4 + 1e-12)


def test_residuals_point_away_from_the_sensor():
    # a car seen from behind at any azimuth: the fit is its rear face (thin, across the
    # line of sight); the car extends 2.2 m further away. The coded residual must be the
    # same everywhere, or a regressor could not learn to extend I / L shapes.
    a = np.linspace(-np.pi, np.pi, 13)
    r = 15.0
    fit = np.c_[r * np.cos(a), r * np.sin(a), np.full(13, -1.0), np.full(13, 1.8),
                np.full(13, 0.1), np.full(13, 1.5), a + np.pi / 2]
    fit[:, 6] = (fit[:, 6] + np.pi / 2) % np.pi - np.pi / 2
    gt = np.c_[(r + 2.2) * np.cos(a), (r + 2.2) * np.sin(a), np.full(13, -1.0),
               np.full(13, 4.5), np.full(13, 1.8), np.full(13, 1.5), a]
    d = encode_residuals(fit, gt)
    np.testing.assert_allclose(d, np.tile(d[0], (13, 1)), atol=1e-9)
    np.testing.assert_allclose(d[0, [0, 1, 3, 4]], [0.0, 2.2, 0.0, 4.4], atol=1e-9)


def test_proposal_targets_label_the_car_and_not_the_clutter():
    sc, gt = car_scene(12.0, -4.0, 0.4)
    props = compute_proposals(sc.xyz, sc.intensity)
    frame = SimpleNamespace(instance=sc.instance, gt_boxes=gt, gt_class=np.array([10]),
                            gt_instance=np.array([1]),
                            gt_num_points=np.array([(sc.instance == 1).sum()]))
    t = proposal_targets(props, frame)
    car_pts = np.flatnonzero(sc.instance == 1)
    on_car = np.array([np.isin(props.clusters.members(c), car_pts).mean() for c in props.cluster])
    whole = np.array([np.isin(car_pts, props.clusters.members(c)).mean() for c in props.cluster])
    np.testing.assert_allclose(t.purity, on_car)
    np.testing.assert_allclose(t.coverage, np.where(on_car > 0, whole, 0.0))
    # the loose rule: mostly the car's points, or BEV IoU >= 0.3; fragments are background
    car = ((on_car >= 0.5) & (whole >= 0.5)) | (t.iou >= 0.3)
    assert car.any() and (~car & (on_car > 0.9)).any()
    np.testing.assert_array_equal(t.label, np.where(car, 1, 0))
    np.testing.assert_array_equal(t.gt_index, np.where(car, 0, -1))
    fg = t.label > 0
    assert np.isfinite(t.deltas[fg]).all() and np.isnan(t.deltas[~fg]).all()
    np.testing.assert_allclose(iou_bev_pairs(decode_residuals(props.boxes[fg], t.deltas[fg]),
                                             np.repeat(gt, fg.sum(), axis=0)), 1.0, atol=1e-9)


def test_config_round_trip():
    cfg = DetectorConfig(nms_iou=0.3, score_threshold=0.2)
    assert DetectorConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


# ------------------------------------------------------------------ trained models
@pytest.fixture(scope="module")
def detector():
    return ReferenceDetector()


@needs_models
@pytest.mark.parametrize("azimuth_deg, yaw", [(20.0, 0.0), (-45.0, 0.0)])
def test_isolated_car_at_10m(detector, azimuth_deg, yaw):
    """Acceptance: a lone car 10 m away is found, as a car, with BEV IoU > 0.7."""
    a = np.radians(azimuth_deg)
    sc, gt = car_scene(10 * np.cos(a), 10 * np.sin(a), yaw)
    out = detector.detect(sc.xyz, sc.intensity, sc.ring)
    assert len(out.keep) >= 1
    top = out.keep[0]
    assert out.labels[top] == 10 and out.scores[top] > 0.5
    assert iou_bev(out.boxes[top:top + 1], gt)[0, 0] > 0.7
    # the car is seen by several proposals, all suppressed by the detection
    assert len(out.preimage(top)) >= 3


def check_nms_bookkeeping(boxes, scores, keep, sup, cfg):
    """The NMS invariants every output must satisfy (also used by test_multihead)."""
    P = len(scores)
    assert sup.shape == (P,) and len(np.unique(keep)) == len(keep)
    assert np.all((keep >= 0) & (keep < P))
    assert np.all(np.diff(scores[keep]) <= 0)                     # descending score
    assert np.all(sup[keep] == -1)
    assert np.all(scores[keep] >= cfg.score_threshold)
    low = scores < cfg.score_threshold
    assert np.all(sup[low] == -1) and not np.isin(keep, np.flatnonzero(low)).any()
    # every other eligible proposal names the survivor that suppressed it
    rest = np.setdiff1d(np.flatnonzero(~low), keep)
    if len(keep) < cfg.max_detections:
        assert np.all(sup[rest] >= 0)
    j = np.flatnonzero(sup >= 0)
    assert np.isin(sup[j], keep).all()
    assert np.all(scores[sup[j]] >= scores[j])
    assert np.all(iou_bev_pairs(boxes[j], boxes[sup[j]]) > cfg.nms_iou)
    # survivors do not overlap each other above the threshold
    iou = iou_bev(boxes[keep], boxes[keep])
    np.fill_diagonal(iou, 0.0)
    assert np.all(iou <= cfg.nms_iou + 1e-12)


@needs_models
def test_outputs_on_a_simulated_frame_are_consistent(detector):
    f = next(islice(split_frames("reference_test", sequences=[0]), 1))
    out = detector.detect(f.xyz, f.intensity, f.ring)
    cfg = detector.config
    P = len(out.scores)
    assert P > 50 and len(out.keep) > 5
    assert out.boxes.shape == (P, 7) and out.class_probs.shape == (P, len(PROB_NAMES))
    np.testing.assert_allclose(out.class_probs.sum(axis=1), 1.0, atol=1e-5)
    fg = out.class_probs[:, 1:]
    np.testing.assert_array_equal(out.labels, FG_CLASS_IDS[np.argmax(fg, axis=1)])
    np.testing.assert_allclose(out.scores, fg.max(axis=1))
    assert np.all(out.scores >= cfg.proposal_threshold)
    # the proposals contain the survivors: detections are rows of the proposal arrays
    np.testing.assert_array_equal(out.det_boxes, out.boxes[out.keep])
    check_nms_bookkeeping(out.boxes, out.scores, out.keep, out.suppressed_by, cfg)
    # pre-images partition the eligible proposals
    eligible = np.flatnonzero(out.scores >= cfg.score_threshold)
    pre = np.concatenate([out.preimage(k) for k in out.keep])
    np.testing.assert_array_equal(np.sort(pre), eligible)
    assert np.median([len(out.preimage(k)) for k in out.keep]) >= 2
    assert np.isfinite(out.boxes).all() and np.all(out.boxes[:, 3:6] > 0)
    assert {"ground", "cluster", "box_fit", "features", "models", "nms"} <= set(out.timings_ms)


# ------------------------------------------------------------------ training round trip
def test_train_save_load_detect(tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_SIM_CACHE", "")                 # tiny split: do not cache it
    info = train_detector(tmp_path, sequences=[0, 1], frames=2, log=lambda *a: None)
    assert info["n_candidates"] > 1000
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["detector.json", "detector_box.ubj", "detector_box.ubj.manifest.json",
                     "detector_classifier.ubj", "detector_classifier.ubj.manifest.json"]
    det = ReferenceDetector(tmp_path, nms_iou=0.2)
    assert det.config.nms_iou == 0.2
    sc, _ = car_scene(10.0, 3.0, 0.2)
    out = det.detect(sc.xyz, sc.intensity)
    check_nms_bookkeeping(out.boxes, out.scores, out.keep, out.suppressed_by, det.config)
    # a tampered model is refused by the model store
    p = tmp_path / "detector_box.ubj"
    p.write_bytes(p.read_bytes()[:-10])
    from lidar_quality_core.model_store import ModelStoreError
    with pytest.raises(ModelStoreError):
        ReferenceDetector(tmp_path)
