"""lidar_quality_training.mimo.evaluate: partitions and targets on a hand-made frame, the meta distribution,
and mimo-train + mimo-eval end to end on tiny perception bags."""
import json
import math

import numpy as np
import pytest
from lidar_quality_core.detection_eval import Partition
from lidar_quality_training.mimo.dataset import MimoDataset
from lidar_quality_training.mimo.evaluate import (Detections, annotate, main, meta_distribution,
                                                 regression_gt, split_groups)
from lidar_quality_training.mimo.train import CARD_BEGIN, main as train_main
from mimo_data import perception_bags

NAMES = ("car", "truck", "pedestrian", "cyclist")


def hand_dataset(det_boxes, det_labels, det_scores, gt_boxes, gt_labels, gt_points):
    """A one-frame MimoDataset whose merged and single tables hold the given detections."""
    n, g = len(det_boxes), len(gt_boxes)
    probs = np.zeros((n, 5))
    probs[np.arange(n), det_labels] = det_scores
    probs[:, 0] = 1 - np.asarray(det_scores)
    box = np.asarray(det_boxes, float)
    lab = np.asarray(det_labels)
    sc = np.asarray(det_scores, float)
    z = np.zeros(n)
    tab = dict(X=np.zeros((n, 29)), m_box=box, m_probs=probs, m_label=lab, m_score=sc,
               m_var=np.full((n, 7), 0.1), m_iou_class=z, m_iou_any=z,
               m_frame=np.zeros(n, np.int64), s_box=box, s_probs=probs, s_label=lab,
               s_score=sc, s_var=np.full((n, 7), 0.1), s_iou_class=z, s_iou_any=z,
               s_frame=np.zeros(n, np.int64))
    return MimoDataset(NAMES, tuple(f"f{i}" for i in range(29)), frame_group=np.array(["a"]),
                       frame_source=np.array(["x"]), frame_stamp=np.array([1]),
                       frame_heads=np.array([2]), gt_offsets=np.array([0, g]),
                       gt_box=np.asarray(gt_boxes, float), gt_label=np.array(gt_labels),
                       gt_id=np.array([str(i) for i in range(g)]),
                       gt_points=np.asarray(gt_points), **tab)


def test_partitions_and_scoring_targets_of_a_hand_made_frame():
    car = [10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0]
    ped = [20.0, 5.0, -1.0, 0.6, 0.6, 1.7, 0.0]
    far = [60.0, 0.0, -1.0, 0.6, 0.6, 1.7, 0.0]   # GT with 2 points: ignored
    dets = [car,                                         # car on the car: TP
            [11.6, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0],       # car IoU 0.43: FP_ML
            [10.0, 0.2, -1.0, 4.0, 2.0, 1.5, 0.0],       # truck on the car: FP_ML
            [30.0, -9.0, -1.0, 4.0, 2.0, 1.5, 0.0],      # nothing there: FP_BG
            far]                                          # on the ignored GT: IGNORED
    labels = [1, 1, 2, 1, 3]
    ds = hand_dataset(dets, labels, [0.9, 0.8, 0.7, 0.6, 0.5], [car, ped, far],
                      ["car", "pedestrian", "pedestrian"], [100, 40, 2])
    det = Detections(ds.m_frame, ds.m_box, ds.m_probs, ds.m_label, ds.m_score, ds.m_var,
                     ds.m_iou_class)
    ann = annotate(ds, det, ds.gt_ignore())
    assert ann.part.tolist() == [Partition.TP, Partition.FP_ML, Partition.FP_ML,
                                 Partition.FP_BG, Partition.IGNORED]
    assert ann.target[:4].tolist() == [1, 0, 0, 0]   # TP: its class; every FP: background
    assert ann.gt_row[:4].tolist() == [0, 0, 0, -1]
    split = split_groups(ds)
    assert split[0].tolist() == [] and split[1].tolist() == [0]  # one frame: halves by frame


def test_meta_distribution_puts_the_confidence_on_the_label():
    p = np.array([[0.2, 0.6, 0.1, 0.1, 0.0], [0.0, 1.0, 0.0, 0.0, 0.0]])
    q = meta_distribution(p, np.array([1, 1]), np.array([0.8, 0.3]))
    # row 0: rest 0.4 -> 0.2 shared as 0.2:0.1:0.1
    np.testing.assert_allclose(q[0], [0.1, 0.8, 0.05, 0.05, 0.0])
    np.testing.assert_allclose(q[1], [0.7, 0.3, 0, 0, 0])   # nothing else: background
    np.testing.assert_allclose(q.sum(axis=1), 1.0)


def test_regression_gt_is_the_equivalent_rectangle_nearest_to_the_prediction():
    pred = np.array([[0, 0, 0, 4.0, 2.0, 1.5, 0.1], [0, 0, 0, 4.0, 2.0, 1.5, 0.0]])
    gt = np.array([[0, 0, 0, 2.0, 4.0, 1.5, 0.1 + math.pi / 2],   # l / w swapped
                   [0, 0, 0, 4.0, 2.0, 1.5, math.pi - 0.05]])      # heading flipped
    g = regression_gt(pred, gt)
    np.testing.assert_allclose(g[0], [0, 0, 0, 4.0, 2.0, 1.5, 0.1], atol=1e-12)
    np.testing.assert_allclose(g[1], [0, 0, 0, 4.0, 2.0, 1.5, -0.05], atol=1e-12)
    np.testing.assert_array_equal(regression_gt(pred, gt, heading_aware=True), gt)


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    root = tmp_path_factory.mktemp("mimo_eval")
    train = perception_bags(root / "train", n_sequences=2, n_frames=3, seed=21)
    test = perception_bags(root / "test", n_sequences=2, n_frames=3, seed=22)
    models = root / "models"
    cache = root / "cache"
    assert train_main(["--data", str(train), "--out", str(models), "--cache", str(cache),
                       "--folds", "0", "--quiet"]) == 0
    out, docs = root / "eval", root / "docs"
    assert main(["--data", str(test), "--models", str(models), "--out", str(out), "--cache",
                 str(cache), "--docs", str(docs), "--model-card", str(models / "MODEL_CARD.md"),
                 "--es-samples", "100", "--quiet"]) == 0
    return out, docs, models


def test_cli_writes_report_summary_figures_and_card(evaluated):
    out, docs, models = evaluated
    for f in ("report.md", "summary.json", "mimo_reliability.png", "mimo_iou_scatter.png",
              "mimo_qualitative.png"):
        assert (out / f).stat().st_size > 0, f
    for f in ("mimo_qualitative.png", "mimo_reliability.png"):
        assert (docs / f).read_bytes() == (out / f).read_bytes()
    s = json.loads((out / "summary.json").read_text())
    assert set(s["methods"]) == {"single", "merged", "meta", "meta_points"}
    assert s["recal_groups"] == ["bags/seq_00"] and s["eval_groups"] == ["bags/seq_01"]
    for name, r in s["methods"].items():
        assert 0 < r["map_bev50"] <= 1
        assert r["counts"]["TP"] > 0 and r["counts"]["FP_BG"] >= 0
        for which in ("raw", "recalibrated"):
            u = r[which]
            assert u["n"] == u["count_TP"] + u["count_FP_ML"] + u["count_FP_BG"]
            assert u["nll_cls_TP"] >= 0 and 0 <= u["brier_TP"] <= 2
            assert u["mce_cls"] is not None and 0 <= u["mce_cls"] <= 1
            assert u["nll_reg_TP"] is not None and u["energy_TP"] > 0
        assert r["recalibrated"]["n"] <= r["raw"]["n"]
    # the meta model only rescores the merged detections: same partitions
    assert s["methods"]["meta"]["counts"]["TP"] == s["methods"]["merged"]["counts"]["TP"]
    assert set(s["meta_quality"]) == {"merged", "meta", "meta_points"}
    assert s["acceptance"]["checked"] is True
    assert s["qualitative"]["merged"] > 0
    report = (out / "report.md").read_text()
    assert "merged heads + meta model" in report
    assert "![qualitative](mimo_qualitative.png)" in report
    card = (models / "MODEL_CARD.md").read_text()
    assert CARD_BEGIN in card and "Not evaluated yet" not in card and "bags/seq_01" in card
