"""lms-eval end to end on tiny data: Table I, held-out with the trained models (on a
SemanticKITTI-style directory), Table II, figures, report and summary."""
import dataclasses
import json

import numpy as np
import pytest
from lms_data import COLUMNS, perception_bags, semantickitti_dir
from lidar_quality_training.lms import evaluate, train
from lidar_quality_training.lms.dataset import build_dataset
from lms_ros.pipeline import LmsSettings

SETTINGS = LmsSettings(width=COLUMNS)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("lms_eval")
    return {"bags": perception_bags(root / "pb", n_sequences=2, n_frames=4),
            "sk": semantickitti_dir(root / "sk", n_frames=3), "root": root}


def test_greedy_selects_named_metrics(data):
    full = build_dataset(data["bags"], SETTINGS, block_frames=2, quiet=True)
    names = ["mean_E", "mean_D", "var_V_bd", "mean_r", "S", "S_rel", "SP", "P_road", "P_car"]
    ds = dataclasses.replace(full, X=full.columns(names), names=tuple(names))
    g = evaluate.greedy(ds, steps=2, search_folds=2, search_rows=None, n_folds=2,
                        score_kind="xgboost", quiet=True)
    for task in ("classification", "regression"):
        d = g[task]
        assert len(d["selected"]) == 2 and set(d["selected"]) <= set(ds.names)
        assert len(set(d["selected"])) == 2 and d["scores"][1] >= d["scores"][0]
        assert d["scores"][0] > (0.5 if task == "classification" else 0.0)
        key = "auroc" if task == "classification" else "r2"
        assert len(d["rescore"]) == 2 and np.isfinite(d["rescore"][1][key])


def test_cli_writes_report_summary_and_figures(data, tmp_path):
    common = ["--width", str(COLUMNS), "--block-frames", "2", "--cache", str(tmp_path / "c"),
              "--quiet"]
    models = tmp_path / "models"
    assert train.main(["--data", str(data["bags"]), "--out", str(models), "--folds", "0",
                       *common]) == 0
    out, docs = tmp_path / "eval", tmp_path / "docs" / "lms_quality.png"
    # held out: the SemanticKITTI-style directory (figure 1) and, reused, the bags
    assert evaluate.main(["--train", str(data["bags"]), "--test", str(data["sk"]), str(data["bags"]),
                          "--models", str(models), "--out", str(out), "--folds", "2",
                          "--greedy-steps", "1", "--greedy-folds", "2", "--greedy-rows", "300",
                          "--figure-frame", "1", "--docs-figure", str(docs), "--model-card",
                          *common]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for s in ("lms", "no_features", "entropy"):
        t = summary["table1"][s]
        for part in ("train", "val"):
            acc, sd = t["classification"][part]["accuracy"]
            assert 0 <= acc <= 1 and sd >= 0
        assert np.isfinite(t["regression"]["train"]["r2"][0])
        h = summary["heldout"][s]
        assert 0 <= h["classification"]["auroc"] <= 1 and np.isfinite(h["regression"]["r2"])
    assert summary["test_data"]["n_sequences"] == 3 and summary["test_data"]["n_frames"] == 11
    other = summary["heldout_other_rows"]      # the bags once more, rows without the ring
    assert other["ring_from"] == "segmentation" and other["n_segments"] > 0
    assert 0 <= other["classification"]["auroc"] <= 1
    assert summary["n_point_feature_metrics"] == 50
    assert summary["feature_sets"]["entropy"] == ["mean_E"]
    assert isinstance(summary["acceptance"]["passed"], bool)
    assert summary["figure1"]["n_rated"] > 0
    assert len(summary["greedy"]["regression"]["rescore"]) == 1
    report = (out / "report.md").read_text()
    for text in ("Table I", "Table II", "Held-out", "LMS w/o features", "Entropy",
                 "naive baseline", "figure1.png"):
        assert text in report
    for png in ("reliability_cv.png", "reliability_heldout.png", "scatter_cv.png",
                "scatter_heldout.png", "figure1.png", "greedy_classification.png",
                "greedy_regression.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
        assert png in report
    assert docs.read_bytes() == (out / "figure1.png").read_bytes()
    card = models / "MODEL_CARD.md"
    assert card.read_text().count("## Held-out evaluation") == 1
    evaluate.update_model_card(card, summary)          # a second run replaces the section
    text = card.read_text()
    assert text.count("## Held-out evaluation") == 1 and text.count("## Limits") == 1
    assert text.index("## Held-out evaluation") < text.index("## Limits")


def test_eval_refuses_models_of_another_schema(data, tmp_path):
    from lidar_quality_core.model_store import ModelStoreError

    ds = build_dataset(data["bags"], SETTINGS, block_frames=2, quiet=True)
    other = ds.subset(np.arange(len(ds)))
    other.names = tuple(f"m{k}" for k in range(len(ds.names)))
    from lidar_quality_core import meta_model

    clf, reg = train.fit_pair(ds)
    meta_model.save_pair(tmp_path, "lms", clf, reg, other.names)
    with pytest.raises(ModelStoreError):
        evaluate.heldout(ds, ds, tmp_path)
