"""lmd-train end to end on tiny perception bags: one verified model pair per mode where the
node looks for them, manifests whose figures are what the models do, a model card, and
the same models from the same command."""
import json

import numpy as np
import pytest
from lidar_quality_core import metrics as M
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.model_store import read_manifest
from lmd_bags import write_split
from lmd_ros import dataset as D
from lmd_ros import train
from lmd_ros.pipeline import LmdSettings, default_model_paths


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("lmd_train")
    write_split(root / "meta_train", 3, 2, seed0=0)
    write_split(root / "meta_test", 2, 2, seed0=500)
    return root


def run(data, out, *extra):
    return train.main(["--train", str(data / "meta_train"), "--test", str(data / "meta_test"),
                       "--out", str(out), "--cache", str(data / "cache"), "--cv-folds", "2",
                       "--quiet", *extra])


def test_train_writes_verified_models_per_mode(data, tmp_path, monkeypatch, capsys):
    out = tmp_path / "models" / "lmd"
    assert run(data, out) == 0
    printed = capsys.readouterr().out
    monkeypatch.setenv("LQ_MODELS_DIR", str(tmp_path / "models"))
    for mode in train.MODES:
        settings = LmdSettings(proposal_mode=mode)
        cpath, rpath = default_model_paths(mode)
        assert cpath.exists() and rpath.exists()
        models = MetaModels(cpath, rpath, settings.feature_names())  # schema, sha, task checked
        test = D.load_bags([data / "meta_test"], [D.settings_for(mode)], progress=False)[mode]
        trn = D.load_bags([data / "meta_train"], [D.settings_for(mode)], progress=False)[mode]
        conf, iou = models.predict(test.X)
        man = read_manifest(cpath)
        td = man["training_data"]
        assert td["frames"] == 6 and td["boxes"] == len(trn) and td["groups"] == 3
        assert td["sources"] == ["meta_train/seq_00", "meta_train/seq_01", "meta_train/seq_02"]
        assert td["settings"]["proposal_mode"] == mode and td["tp_rule"] == "IoU_BEV >= 0.5"
        assert td["held_out"]["boxes"] == len(test)
        held = man["metrics"]["held_out"]
        assert held["auroc"] == pytest.approx(M.auroc(test.tp, conf), abs=1e-5)
        assert held["ece"] == pytest.approx(M.ece(test.tp, conf), abs=1e-5)
        score = man["metrics"]["held_out_detector_score"]
        assert score["auroc"] == pytest.approx(M.auroc(test.tp, test.score), abs=1e-5)
        rman = read_manifest(rpath)
        assert rman["metrics"]["held_out"]["r2"] == pytest.approx(M.r2(test.iou, iou), abs=1e-5)
        assert len(rman["metrics"]["cv"]["r2"]) == 2  # mean, std
        assert cpath.stat().st_size + rpath.stat().st_size < 2_000_000
        assert f"{mode}: {len(trn)} training boxes" in printed
    card = (out / "MODEL_CARD.md").read_text()
    assert "lmd-train --train" in card and "| threshold | 90 |" in card and "| none | 17 |" in card


def test_same_command_same_models(data, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert run(data, a, "--modes", "none", "--no-model-card") == 0
    assert run(data, b, "--modes", "none", "--no-model-card") == 0
    assert not (a / "MODEL_CARD.md").exists()
    assert sorted(p.name for p in a.iterdir()) == [
        "lmd_none_classifier.joblib", "lmd_none_classifier.joblib.manifest.json",
        "lmd_none_regressor.joblib", "lmd_none_regressor.joblib.manifest.json"]
    names = LmdSettings(proposal_mode="none").feature_names()
    X = D.load_bags([data / "meta_test"], [D.settings_for("none")], progress=False)["none"].X
    pa = MetaModels(a / "lmd_none_classifier.joblib", a / "lmd_none_regressor.joblib", names)
    pb = MetaModels(b / "lmd_none_classifier.joblib", b / "lmd_none_regressor.joblib", names)
    for u, v in zip(pa.predict(X), pb.predict(X)):
        np.testing.assert_array_equal(u, v)
    ma = json.loads((a / "lmd_none_classifier.joblib.manifest.json").read_text())
    mb = json.loads((b / "lmd_none_classifier.joblib.manifest.json").read_text())
    assert ma["metrics"] == mb["metrics"]
