"""mimo-train end to end on tiny perception bags: two verified model pairs and a model card
that the node's model loading accepts."""
import json

import numpy as np
import pytest
from lidar_quality_core import metrics
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.model_store import ModelStoreError
from mimo_ros.dataset import load_bags
from mimo_ros.pipeline import MimoSettings, default_model_paths
from mimo_ros.train import CARD_BEGIN, CARD_END, main
from mimo_data import perception_bags


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("mimo_train")
    bags = perception_bags(root, n_sequences=2, n_frames=3, seed=11)
    out = root / "mimo"  # LQ_MODELS_DIR=root makes it the node's default model directory
    assert main(["--data", str(bags), "--out", str(out), "--cache", str(root / "cache"),
                 "--folds", "2", "--quiet"]) == 0
    return bags, out, root


def test_cli_writes_both_pairs_with_manifests_and_card(trained, monkeypatch):
    bags, out, root = trained
    names = {p.name for p in out.iterdir()}
    for prefix in ("mimo", "mimo_points"):
        for kind in ("classifier", "regressor"):
            assert f"{prefix}_{kind}.joblib" in names
            assert f"{prefix}_{kind}.joblib.manifest.json" in names
    man = json.loads((out / "mimo_classifier.joblib.manifest.json").read_text())
    assert man["task"] == "classification"
    assert tuple(man["feature_names"]) == MimoSettings().feature_names()
    assert man["training_data"]["groups"] == ["bags/seq_00", "bags/seq_01"]
    assert man["metrics"]["cv_folds"] == 2 and "auroc" in man["metrics"]["cv_val"]
    card = (out / "MODEL_CARD.md").read_text()
    assert CARD_BEGIN in card and CARD_END in card and "| mimo_points |" in card
    # the node's default paths name these files
    monkeypatch.setenv("LQ_MODELS_DIR", str(root))
    for use_points, prefix in ((False, "mimo"), (True, "mimo_points")):
        c, r = default_model_paths(use_points)
        assert (c, r) == (out / f"{prefix}_classifier.joblib", out / f"{prefix}_regressor.joblib")


def test_models_load_through_the_store_and_rank_the_training_data(trained):
    bags, out, root = trained
    ds = load_bags([bags], cache_dir=root / "cache", progress=False)
    for use_points, prefix in ((False, "mimo"), (True, "mimo_points")):
        names = MimoSettings(use_points=use_points).feature_names()
        mm = MetaModels(out / f"{prefix}_classifier.joblib", out / f"{prefix}_regressor.joblib",
                        names)
        X, _ = ds.features(use_points)
        conf, iou = mm.predict(X)
        assert conf.shape == iou.shape == (len(ds),)
        assert np.all((conf >= 0) & (conf <= 1)) and np.all((iou >= 0) & (iou <= 1))
        # fitted on these rows: a real model separates them and tracks the IoU
        assert metrics.auroc(ds.tp, conf) > 0.9
        assert metrics.r2(ds.m_iou_class, iou) > 0.5
    # the schema is enforced: the statistics model refuses the point features' schema
    with pytest.raises(ModelStoreError):
        MetaModels(out / "mimo_classifier.joblib", out / "mimo_regressor.joblib",
                   MimoSettings(use_points=True).feature_names())
