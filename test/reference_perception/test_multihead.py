"""Tests of reference_perception.multihead: variance bookkeeping, the trained K heads
(shared proposals, logits, variances, per-head NMS; acceptance: the heads disagree more on
far objects than on near ones, measured) and a small K-head training round trip."""
from itertools import islice

import numpy as np
import pytest

from lidar_sim.frames import split_frames
from reference_perception.detector import FG_CLASS_IDS, PROB_NAMES, default_model_dir
from reference_perception.multihead import (MAX_HEADS, MultiHeadDetector, head_disagreement,
                                            local_to_param_variance, summarize_disagreement,
                                            train_multihead)

MODEL_DIR = default_model_dir()
needs_models = pytest.mark.skipif(
    not (MODEL_DIR / "multihead.json").is_file(),
    reason=f"no trained heads in {MODEL_DIR} (python -m reference_perception.multihead train)")


def check_nms(boxes, scores, keep, sup, cfg):
    from lidar_quality_core.iou import iou_bev, iou_bev_pairs
    assert np.all(sup[keep] == -1) and np.all(np.diff(scores[keep]) <= 0)
    j = np.flatnonzero(sup >= 0)
    assert np.isin(sup[j], keep).all() and np.all(scores[sup[j]] >= scores[j])
    assert np.all(iou_bev_pairs(boxes[j], boxes[sup[j]]) > cfg.nms_iou)
    rest = np.setdiff1d(np.flatnonzero(scores >= cfg.score_threshold), keep)
    assert np.all(sup[rest] >= 0)
    iou = iou_bev(boxes[keep], boxes[keep])
    np.fill_diagonal(iou, 0.0)
    assert np.all(iou <= cfg.nms_iou + 1e-12)


def test_local_variances_rotate_into_the_sensor_frame():
    boxes = np.zeros((3, 7))
    boxes[:, 6] = [0.0, np.pi / 2, np.pi / 4]
    local = np.tile([4.0, 1.0, 0.1, 0.2, 0.3, 0.4, 0.05], (3, 1))
    v = local_to_param_variance(boxes, local)
    np.testing.assert_allclose(v[:, 0], [4.0, 1.0, 2.5], atol=1e-12)   # along the yaw: x
    np.testing.assert_allclose(v[:, 1], [1.0, 4.0, 2.5], atol=1e-12)
    np.testing.assert_allclose(v[:, 2:], local[:, 2:])
    assert np.all(local_to_param_variance(boxes, -local) > 0)          # floored


@pytest.fixture(scope="module")
def mimo():
    return MultiHeadDetector()


@pytest.fixture(scope="module")
def test_frames():
    # the first frame of every reference_test sequence (held out from training)
    return [next(islice(split_frames("reference_test", sequences=[s]), 1)) for s in range(4)]


@needs_models
def test_heads_share_proposals_and_carry_logits_and_variances(mimo, test_frames):
    f = test_frames[0]
    props = mimo.proposals(f.xyz, f.intensity, f.ring)
    out = mimo.detect_proposals(props)
    assert out.num_heads == mimo.num_heads == len(out) >= 2
    assert list(out) == out.heads and out[1] is out.heads[1]
    P = len(out.candidate)
    assert P > 50 and out.fitted_boxes.shape == (P, 7)
    np.testing.assert_array_equal(out.fitted_boxes, props.boxes[out.candidate])
    for h in out.heads:
        assert h.logits.shape == (P, len(PROB_NAMES)) and h.variances.shape == (P, 7)
        soft = np.exp(h.logits - h.logits.max(axis=1, keepdims=True))
        np.testing.assert_allclose(soft / soft.sum(axis=1, keepdims=True), h.class_probs,
                                   atol=1e-6)
        np.testing.assert_array_equal(h.labels, FG_CLASS_IDS[np.argmax(h.class_probs[:, 1:], 1)])
        assert np.all(h.variances > 0) and np.isfinite(h.variances).all()
        assert len(h.keep) > 5
        check_nms(h.boxes, h.scores, h.keep, h.suppressed_by, mimo.config)
    # the heads are different models: not identical outputs
    a, b = out.heads[0], out.heads[1]
    assert not np.allclose(a.class_probs, b.class_probs)
    assert not np.allclose(a.boxes, b.boxes)
    # proposals: every candidate some head scores >= proposal_threshold
    best = np.max([h.scores for h in out.heads], axis=0)
    assert np.all(best >= mimo.config.proposal_threshold)
    # fewer heads on request
    assert MultiHeadDetector(num_heads=1).detect_proposals(props).num_heads == 1


@needs_models
def test_heads_disagree_more_on_far_objects(mimo, test_frames):
    """Acceptance: head disagreement on proposals of far (> 40 m) ground-truth objects
    exceeds that on near (< 20 m) ones, for the scores and the boxes (measured)."""
    parts = []
    for f in test_frames:
        props = mimo.proposals(f.xyz, f.intensity, f.ring)
        parts.append(head_disagreement(mimo.detect_proposals(props), props, f))
    res = summarize_disagreement(parts, log=lambda *a: None)
    near, far = res["near"], res["far"]
    assert near["n"] > 100 and far["n"] > 50
    assert far["score_std"] > 1.5 * near["score_std"]
    assert far["centre_spread"] > near["centre_spread"]
    assert far["box_1_iou"] > near["box_1_iou"]


def test_train_two_heads_round_trip(tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_SIM_CACHE", "")
    with pytest.raises(ValueError):
        train_multihead(tmp_path, num_heads=MAX_HEADS + 1)
    train_multihead(tmp_path, num_heads=2, sequences=[0, 1], frames=2, log=lambda *a: None)
    for k in range(2):
        for part in ("classifier", "box", "variance"):
            assert (tmp_path / f"head{k}_{part}.ubj").is_file()
            assert (tmp_path / f"head{k}_{part}.ubj.manifest.json").is_file()
    m = MultiHeadDetector(tmp_path)
    assert m.num_heads == 2
    with pytest.raises(ValueError):
        MultiHeadDetector(tmp_path, num_heads=3)
    f = next(islice(split_frames("reference_train", sequences=[0], frames=2), 1))
    out = m.detect(f.xyz, f.intensity)
    for h in out.heads:
        check_nms(h.boxes, h.scores, h.keep, h.suppressed_by, m.config)
        assert np.all(h.variances > 0)
