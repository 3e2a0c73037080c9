"""lms-train: feature sets, grouped cross validation, the CLI end to end, the node's
frame processor running the trained models, and the same models from a feature table."""
import json

import numpy as np
import pytest
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.model_store import read_manifest
from lidar_quality_ros.perception_bag import perception_frames
from lms_data import COLUMNS, perception_bags
from lidar_quality_training.lms.dataset import build_dataset
from lms_ros.pipeline import LmsProcessor, LmsSettings
from lidar_quality_training.lms.train import cross_validate_pair, feature_set, main

SETTINGS = LmsSettings(width=COLUMNS)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return perception_bags(tmp_path_factory.mktemp("lms_train") / "pb", n_sequences=2,
                           n_frames=4)


def test_feature_sets():
    names = SETTINGS.metric_names()
    assert feature_set(names, "lms") == list(names)
    assert feature_set(names, "entropy") == ["mean_E"]
    nf = feature_set(names, "no_features")
    gone = [n for n in names if n not in nf]
    # the 5 point-cloud heatmaps x, y, z, intensity, range x 10 statistics
    assert len(gone) == 50 and len(nf) == 86 + 2 * 14 - 50
    assert {n.split("_")[1] for n in gone} == {"x", "y", "z", "i", "r"}
    for keep in ("mean_E", "var_D_bd", "mean_V_rel_in", "S", "S_rel_in", "SP", "N_car",
                 "P_road", "P_traffic-sign"):
        assert keep in nf
    with pytest.raises(ValueError):
        feature_set(names, "nope")


def test_cross_validation_over_subsequences(bags):
    ds = build_dataset(bags, SETTINGS, block_frames=2, quiet=True)
    cv = cross_validate_pair(ds, feature_set(ds.names, "no_features"), n_folds=3)
    for task, keys in (("classification", {"accuracy", "auroc", "auprc_fp", "ece"}),
                       ("regression", {"r2", "mae"})):
        assert keys <= set(cv[task]["val"]) and len(cv[task]["folds"]) == 3
        assert np.isfinite(cv["oof"][task]).all()
    # a group (sub-sequence) is never split between folds
    for g in np.unique(ds.group):
        assert len(np.unique(cv["fold"][ds.group == g])) == 1
    # the models learn something: better than the constant on the training folds
    assert cv["classification"]["train"]["auroc"][0] > 0.8
    assert cv["regression"]["train"]["r2"][0] > 0.3


def test_cli_trains_loadable_models_the_node_runs(bags, tmp_path):
    out = tmp_path / "models"
    args = ["--data", str(bags), "--folds", "2", "--block-frames", "2", "--width", str(COLUMNS),
            "--cache", str(tmp_path / "cache"), "--quiet"]
    assert main([*args, "--out", str(out)]) == 0
    cpath, rpath = out / "lms_classifier.joblib", out / "lms_regressor.joblib"
    card = (out / "MODEL_CARD.md").read_text()
    assert "lms-train" in card and "cross validation" in card
    man = read_manifest(cpath)
    assert man["feature_names"] == list(SETTINGS.metric_names())
    td = man["training_data"]
    assert td["n_frames"] == 8 and td["n_sequences"] == 2 and td["settings"]["width"] == COLUMNS
    assert set(man["metrics"]["cv_val"]) >= {"accuracy", "auroc", "auprc_fp"}
    assert cpath.stat().st_size + rpath.stat().st_size < 2_000_000
    models = MetaModels(cpath, rpath, SETTINGS.metric_names())
    assert set(models.domain_profile.quantities) == set(SETTINGS.metric_names())
    # the node's frame work with these models
    proc = LmsProcessor(SETTINGS, models)
    f = next(perception_frames(sorted(bags.iterdir())[0], want=("points", "segmentation")))
    res = proc.process(f.points, f.segmentation)
    kept = res.result.kept_ids
    assert len(kept) > 10
    assert np.isfinite(res.confidence[kept]).all() and np.isfinite(res.predicted_iou[kept]).all()
    assert ((res.confidence[kept] >= 0) & (res.confidence[kept] <= 1)).all()
    # deterministic: the same command gives the same predictions
    out2 = tmp_path / "again"
    assert main([*args, "--out", str(out2), "--folds", "0"]) == 0
    again = MetaModels(out2 / "lms_classifier.joblib", out2 / "lms_regressor.joblib",
                       SETTINGS.metric_names())
    X = res.result.features
    for a, b in zip(models.predict(X), again.predict(X)):
        np.testing.assert_array_equal(a, b)
    json.dumps(man)  # the manifest holds plain JSON


# ---------------------------------------------------------------- issue 14: no silent failure
def _main(bags, out, *extra):
    return main(["--data", *map(str, bags), "--width", str(COLUMNS), "--cache",
                 str(bags[0].parent.parent / "cache"), "--quiet", "--out", str(out), *extra])


def test_cv_folds_0_trains_without_cross_validation_and_says_so(bags, tmp_path):
    assert _main([bags], tmp_path, "--cv-folds", "0", "--block-frames", "2") == 0
    td = read_manifest(tmp_path / "lms_classifier.joblib")["training_data"]
    assert td["cv_folds"] == 0 and td["cross_validation"] == "skipped: --cv-folds 0"
    assert "No cross validation (`--cv-folds 0`)." in (tmp_path / "MODEL_CARD.md").read_text()


def test_one_bag_trains_with_subsequence_folds_or_says_why_not(bags, tmp_path, capsys):
    one = sorted(bags.iterdir())[:1]
    # 4 frames in blocks of 2: two groups, cross validation runs on one bag
    assert _main(one, tmp_path / "a", "--cv-folds", "3", "--block-frames", "2") == 0
    td = read_manifest(tmp_path / "a" / "lms_classifier.joblib")["training_data"]
    assert td["n_sequences"] == 1 and td["n_groups"] == 2 and td["cv_folds"] == 2
    # one block of 10 frames: one group
    assert _main(one, tmp_path / "b", "--cv-folds", "3") == 2
    err = capsys.readouterr().err
    assert err.startswith("lms-train: grouped cross validation needs at least 2 "
                          "sub-sequences of 10 frames (groups), the training data has 1")
    assert "--block-frames" in err and "--cv-folds 0" in err and "Traceback" not in err
    assert not (tmp_path / "b" / "lms_classifier.joblib").exists()


def test_model_card_names_the_bags_and_says_simulated_only_for_ours(bags, tmp_path,
                                                                    monkeypatch):
    from lidar_quality_core import meta_model

    assert _main([bags], tmp_path / "a", "--cv-folds", "0") == 0
    card = (tmp_path / "a" / "MODEL_CARD.md").read_text()
    paths = ", ".join(f"`{p}`" for p in sorted(bags.iterdir()))
    assert f"- Perception bags: {paths}." in card
    assert "simulated" not in card and "Trained on the data named above" in card
    monkeypatch.setattr(meta_model, "SIMULATED_DATA_DIR", bags.parent)
    (bags / ".done").touch()  # as `make meta-data` leaves a simulated split
    try:
        assert _main([bags], tmp_path / "b", "--cv-folds", "0") == 0
    finally:
        (bags / ".done").unlink()
    card = (tmp_path / "b" / "MODEL_CARD.md").read_text()
    assert "Trained on simulated HDL-64 scans" in card and paths in card


# ---------------------------------------------------------------- issue 20: feature tables
def test_feature_table_trains_the_models_the_bags_train(bags, tmp_path, capsys):
    tables = tmp_path / "tables"
    common = ["--folds", "2", "--block-frames", "2"]
    assert _main([bags], tmp_path / "unused", *common, "--export-features", str(tables),
                 "--export-only") == 0
    assert f"wrote {tables / 'lms_points.parquet'}" in capsys.readouterr().out
    assert not (tmp_path / "unused").exists()
    assert _main([bags], tmp_path / "a", *common) == 0
    assert main(["--features", str(tables), "--out", str(tmp_path / "b"), "--quiet",
                 *common]) == 0
    ma, mb = (read_manifest(tmp_path / d / "lms_classifier.joblib") for d in "ab")
    assert ma["metrics"] == mb["metrics"]  # the same folds and figures
    ta, tb = ma["training_data"], mb["training_data"]
    for k in ("sequences", "n_frames", "n_segments", "n_groups", "block_frames", "settings",
              "excluded_small_segments", "dropped_undefined_iou", "ignore_label", "ring_from"):
        assert ta[k] == tb[k], k
    assert tb["sources"] == [str(tables / "lms_points.parquet")]
    assert tb["data"]["sources"] == [{"kind": "feature_table", "path": tb["sources"][0]}]
    ds = build_dataset(bags, SETTINGS, block_frames=2, quiet=True)
    pa, pb = (MetaModels(tmp_path / d / "lms_classifier.joblib",
                         tmp_path / d / "lms_regressor.joblib", SETTINGS.metric_names(),
                         settings=SETTINGS, method="lms") for d in "ab")
    for u, v in zip(pa.predict(ds.X), pb.predict(ds.X)):
        np.testing.assert_array_equal(u, v)
    card = (tmp_path / "b" / "MODEL_CARD.md").read_text()
    assert f"- Feature tables (Parquet): `{tables / 'lms_points.parquet'}`." in card
    assert main(["--features", str(tables), "--data", str(bags), "--out",
                 str(tmp_path / "c"), "--quiet"]) == 2
    assert "lms-train: --features replaces --data" in capsys.readouterr().err
