"""lmd-train end to end on tiny perception bags: one verified model pair per mode where the
node looks for them, manifests whose figures are what the models do, a model card, the
same models from the same command, and from the feature tables of the same bags."""
import json

import numpy as np
import pytest
from lidar_quality_core import metrics as M
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.model_store import read_manifest
from lmd_bags import write_split
from lidar_quality_training.lmd import dataset as D
from lidar_quality_training.lmd import train
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
        # the training data's domain profile: every feature, the scores, frames' points
        prof = models.domain_profile
        assert set(prof.quantities) == {*settings.feature_names(), "detector score",
                                        "points per frame"}
        assert prof.quantities["detector score"].count == len(trn)
        assert prof.quantities["detector score"].median == pytest.approx(
            float(np.median(trn.score)), abs=1e-5)
        assert prof.quantities["points per frame"].count == 6
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


# ---------------------------------------------------------------- issue 14: no silent failure
def _run_one(data, out, *extra, train_bags=None):
    return train.main(["--train", *(str(b) for b in (train_bags or [data / "meta_train"])),
                       "--test", "--out", str(out), "--cache", str(data / "cache"),
                       "--modes", "none", "--quiet", *extra])


def test_cv_folds_0_trains_without_cross_validation_and_says_so(data, tmp_path):
    out = tmp_path / "m"
    assert _run_one(data, out, "--cv-folds", "0") == 0
    man = read_manifest(out / "lmd_none_classifier.joblib")
    assert man["training_data"]["cv_folds"] == 0
    assert man["training_data"]["cross_validation"] == "skipped: --cv-folds 0"
    assert "cv" not in man["metrics"]
    card = (out / "MODEL_CARD.md").read_text()
    assert "No cross validation (`--cv-folds 0`)" in card and "| none | 17 | – | – |" in card


def test_cv_folds_1_is_refused_by_the_argument_parser(data, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        _run_one(data, tmp_path / "m", "--cv-folds", "1")
    assert e.value.code == 2
    assert "must be 0 (no cross validation) or >= 2" in capsys.readouterr().err


def test_one_bag_says_why_cross_validation_cannot_run_then_trains_without(data, tmp_path,
                                                                          capsys):
    one = [data / "meta_train" / "seq_00"]
    out = tmp_path / "m"
    assert _run_one(data, out, train_bags=one) == 2
    err = capsys.readouterr().err
    assert err.startswith("lmd-train: grouped cross validation needs at least 2 sequences")
    assert "the training data has 1" in err and "--cv-folds 0" in err
    assert "Traceback" not in err and not out.exists()
    assert _run_one(data, out, "--cv-folds", "0", train_bags=one) == 0
    assert read_manifest(out / "lmd_none_classifier.joblib")["training_data"]["groups"] == 1


def test_model_card_names_the_bags_and_says_simulated_only_for_ours(data, tmp_path,
                                                                    monkeypatch):
    from lidar_quality_core import meta_model

    out = tmp_path / "m"
    assert _run_one(data, out, "--cv-folds", "2") == 0
    card = (out / "MODEL_CARD.md").read_text()
    bags = [f"`{data / 'meta_train' / f'seq_{k:02d}'}`" for k in range(3)]
    assert f"- Training perception bags: {', '.join(bags)}." in card
    assert "simulated" not in card
    assert "the perception bags named above" in card
    td = read_manifest(out / "lmd_none_classifier.joblib")["training_data"]
    assert td["data"]["simulated"] is False
    assert [s["path"] for s in td["data"]["sources"]] == [b.strip("`") for b in bags]
    # the same bags where `make meta-data` writes its simulated splits: ours
    monkeypatch.setattr(meta_model, "SIMULATED_DATA_DIR", data)
    (data / "meta_train" / ".done").touch()
    try:
        assert _run_one(data, out, "--cv-folds", "2") == 0
    finally:
        (data / "meta_train" / ".done").unlink()
    card = (out / "MODEL_CARD.md").read_text()
    assert "simulated lidar sequences (`lidar_sim`)" in card and bags[0] in card


def test_model_card_of_kitti_data_names_the_directory():
    tr = {"frames": 2, "boxes": 3, "tp": 1, "tp_rate": 1 / 3, "groups": 1, "sources": ["00"],
          "kind": "xgboost", "seed": 0, "cv_folds": 0, "target": "IoU_BEV",
          "tp_rule": "IoU_BEV >= 0.5", "settings": {}, "held_out": None,
          "data": {"simulated": False, "sources": [
              {"kind": "kitti", "path": "/k", "split": "training", "results": "/r",
               "proposals": None}]}}
    res = {"none": {"training": tr, "classifier": {}, "regressor": {}, "n_features": 17,
                    "bytes": 1000}}
    card = train.model_card(res, "lmd-train --kitti-root /k")
    assert ("- Training KITTI object directory `/k` (split `training`), detector results "
            "`/r`, no proposals.") in card
    assert "simulated" not in card and "`label_2`" in card


# ---------------------------------------------------------------- issue 20: feature tables
def test_feature_tables_train_the_models_the_bags_train(data, tmp_path, capsys):
    tables = tmp_path / "tables"
    assert run(data, tmp_path / "unused", "--export-features", str(tables),
               "--export-only") == 0
    printed = capsys.readouterr().out
    for part in ("train", "test"):
        for mode in train.MODES:
            assert f"wrote {tables / part / f'lmd_{mode}.parquet'}" in printed
    assert not (tmp_path / "unused").exists()
    bags, tabs = tmp_path / "from_bags", tmp_path / "from_tables"
    assert run(data, bags, "--modes", "threshold", "none") == 0
    assert train.main(["--features", str(tables / "train"), "--test-features",
                       str(tables / "test"), "--out", str(tabs), "--cv-folds", "2",
                       "--modes", "threshold", "none", "--quiet"]) == 0
    test = D.load_bags([data / "meta_test"], [D.settings_for("threshold")],
                       cache_dir=data / "cache", progress=False)["threshold"]
    for mode in ("threshold", "none"):
        names = LmdSettings(proposal_mode=mode).feature_names()
        X = test.X if mode == "threshold" else test.columns(names)
        pa = MetaModels(bags / f"lmd_{mode}_classifier.joblib",
                        bags / f"lmd_{mode}_regressor.joblib", names)
        pb = MetaModels(tabs / f"lmd_{mode}_classifier.joblib",
                        tabs / f"lmd_{mode}_regressor.joblib", names,
                        settings=LmdSettings(proposal_mode=mode), method="lmd")
        for u, v in zip(pa.predict(X), pb.predict(X)):
            np.testing.assert_array_equal(u, v)
        ma, mb = (read_manifest(d / f"lmd_{mode}_classifier.joblib") for d in (bags, tabs))
        assert ma["metrics"] == mb["metrics"]  # cross validation and held-out figures
        ta, tb = ma["training_data"], mb["training_data"]
        for k in ("frames", "boxes", "tp", "groups", "gt_boxes", "settings", "target"):
            assert ta[k] == tb[k], k
        assert tb["sources"] == [str(tables / "train" / f"lmd_{mode}.parquet")]
        assert tb["held_out"]["sources"] == [str(tables / "test" / f"lmd_{mode}.parquet")]
        assert tb["data"] == {"sources": [{"kind": "feature_table", "path": tb["sources"][0],
                                           "rows": ta["boxes"]}], "simulated": False}
    card = (tabs / "MODEL_CARD.md").read_text()
    line = next(t for t in card.splitlines() if "Training feature tables (Parquet): " in t)
    for mode in ("threshold", "none"):  # one table per mode
        assert f"`{tables / 'train' / f'lmd_{mode}.parquet'}`" in line
    # default: every mode of the tables; held-out bags are read with the tables' settings
    only = tmp_path / "only_none"
    assert train.main(["--features", str(tables / "train" / "lmd_none.parquet"), "--test",
                       str(data / "meta_test"), "--cache", str(data / "cache"), "--out",
                       str(only), "--cv-folds", "2", "--quiet"]) == 0
    assert sorted(p.name for p in only.glob("*.joblib")) == [
        "lmd_none_classifier.joblib", "lmd_none_regressor.joblib"]
    assert read_manifest(only / "lmd_none_classifier.joblib")["metrics"]["held_out"] == \
        read_manifest(bags / "lmd_none_classifier.joblib")["metrics"]["held_out"]


def test_feature_tables_are_one_source_of_data(data, tmp_path, capsys):
    tables = tmp_path / "t"
    assert run(data, tmp_path / "x", "--modes", "none", "--export-features", str(tables),
               "--export-only") == 0
    capsys.readouterr()
    assert train.main(["--features", str(tables / "train"), "--train", str(data / "meta_train"),
                       "--out", str(tmp_path / "m"), "--quiet"]) == 2
    assert "lmd-train: --features replaces --train / --kitti-root" in capsys.readouterr().err
    assert train.main(["--features", str(tables / "train"), "--modes", "exact", "--out",
                       str(tmp_path / "m"), "--quiet"]) == 2
    assert "lmd-train: no LMD table of mode exact" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train.main(["--export-only", "--out", str(tmp_path / "m")])
    assert "--export-only needs --export-features DIR" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
