"""mimo-train end to end on tiny perception bags: two verified model pairs and a model card
that the node's model loading accepts; the same pairs from a feature table."""
import json

import numpy as np
import pytest
from lidar_quality_core import metrics
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.model_store import ModelStoreError
from lidar_quality_training.mimo.dataset import load_bags
from mimo_ros.pipeline import MimoSettings, default_model_paths
from lidar_quality_training.mimo.train import CARD_BEGIN, CARD_END, main
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
        prof = mm.domain_profile
        assert set(prof.quantities) == {*names, "detector score"}
        assert prof.quantities[names[0]].count == np.isfinite(X[:, 0]).sum()
    # the schema is enforced: the statistics model refuses the point features' schema
    with pytest.raises(ModelStoreError):
        MetaModels(out / "mimo_classifier.joblib", out / "mimo_regressor.joblib",
                   MimoSettings(use_points=True).feature_names())


# ---------------------------------------------------------------- issue 14: no silent failure
def test_each_pair_records_its_own_use_points(trained):
    _, out, _ = trained
    for prefix, use_points in (("mimo", False), ("mimo_points", True)):
        man = json.loads((out / f"{prefix}_classifier.joblib.manifest.json").read_text())
        assert man["training_data"]["merge_settings"]["use_points"] is use_points
        assert man["training_data"]["cv_folds"] == 2
    # and the node's settings check accepts each pair for its own use_points
    for use_points, prefix in ((False, "mimo"), (True, "mimo_points")):
        s = MimoSettings(use_points=use_points)
        mm = MetaModels(out / f"{prefix}_classifier.joblib", out / f"{prefix}_regressor.joblib",
                        s.feature_names(), settings=s, method="mimo")
        assert mm.warnings == []


def test_model_card_names_the_bags_not_simulated(trained):
    bags, out, _ = trained
    card = (out / "MODEL_CARD.md").read_text()
    paths = ", ".join(f"`{p}`" for p in sorted(bags.iterdir()))
    assert f"Perception bags with 2 detector heads: {paths}." in card
    assert "imulated" not in card and "Trained on the perception bags named above" in card


def test_cv_folds_0_and_one_bag(trained, tmp_path, capsys):
    bags, _, root = trained
    one = sorted(bags.iterdir())[:1]
    args = ["--data", *map(str, one), "--cache", str(root / "cache"), "--quiet"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mimo-train: grouped cross validation needs at least 2 sequences "
                          "(bags), the training data has 1")
    assert "--cv-folds 0" in err and "Traceback" not in err
    assert not (tmp_path / "a").exists()
    assert main([*args, "--out", str(tmp_path / "b"), "--cv-folds", "0"]) == 0
    man = json.loads((tmp_path / "b" / "mimo_classifier.joblib.manifest.json").read_text())
    assert man["training_data"]["cv_folds"] == 0 and man["metrics"] == {}
    assert man["training_data"]["cross_validation"] == "skipped: --cv-folds 0"
    card = (tmp_path / "b" / "MODEL_CARD.md").read_text()
    assert "No cross validation (`--cv-folds 0`)" in card
    with pytest.raises(SystemExit):
        main([*args, "--out", str(tmp_path / "c"), "--cv-folds", "1"])


def test_model_card_says_simulated_for_our_bags(trained, tmp_path, monkeypatch):
    from lidar_quality_core import meta_model

    bags, _, root = trained
    monkeypatch.setattr(meta_model, "SIMULATED_DATA_DIR", bags.parent)
    (bags / ".done").touch()  # as `make meta-data` leaves a simulated split
    try:
        assert main(["--data", str(bags), "--cache", str(root / "cache"), "--quiet",
                     "--out", str(tmp_path), "--cv-folds", "0"]) == 0
    finally:
        (bags / ".done").unlink()
    card = (tmp_path / "MODEL_CARD.md").read_text()
    assert "Simulated perception bags (`lidar_sim` scenes, reference perception with 2 heads" \
        in card and "Trained on simulated scans" in card


# ---------------------------------------------------------------- issue 20: feature tables
def test_feature_table_trains_the_models_the_bags_train(trained, tmp_path, capsys):
    import pyarrow.parquet as pq

    bags, out, root = trained
    tables = tmp_path / "tables"
    assert main(["--data", str(bags), "--cache", str(root / "cache"), "--export-features",
                 str(tables), "--export-only", "--quiet"]) == 0
    assert f"wrote {tables / 'mimo_points.parquet'}" in capsys.readouterr().out
    assert main(["--features", str(tables), "--out", str(tmp_path / "m"), "--folds", "2",
                 "--quiet"]) == 0
    ds = load_bags([bags], cache_dir=root / "cache", progress=False)
    for use_points, prefix in ((False, "mimo"), (True, "mimo_points")):
        settings = MimoSettings(num_heads=2, use_points=use_points)
        a, b = (MetaModels(d / f"{prefix}_classifier.joblib", d / f"{prefix}_regressor.joblib",
                           settings.feature_names(), settings=settings, method="mimo")
                for d in (out, tmp_path / "m"))
        X, _ = ds.features(use_points)
        for u, v in zip(a.predict(X), b.predict(X)):
            np.testing.assert_array_equal(u, v)
        ma, mb = (json.loads((d / f"{prefix}_classifier.joblib.manifest.json").read_text())
                  for d in (out, tmp_path / "m"))
        assert ma["metrics"] == mb["metrics"]
        ta, tb = ma["training_data"], mb["training_data"]
        for k in ("groups", "frames", "rows", "merge_settings", "cv_folds"):
            assert ta[k] == tb[k], k
        assert tb["sources"] == [str(tables / "mimo_points.parquet")]
    card = (tmp_path / "m" / "MODEL_CARD.md").read_text()
    assert "Feature tables (Parquet) of perception bags with 2 detector heads" in card
    # a table without the point features (process_bags, use_points: false): the mimo pair
    t = pq.read_table(tables / "mimo_points.parquet")
    meta = dict(t.schema.metadata)
    names = json.loads(meta[b"lq.feature_names"])[:len(MimoSettings().feature_names())]
    meta.update({b"lq.mode": b"no_points", b"lq.feature_names": json.dumps(names).encode()})
    cut = t.drop_columns([c for c in t.column_names if c.startswith("feat.")
                          and c[5:] not in names]).replace_schema_metadata(meta)
    (tmp_path / "np").mkdir()
    pq.write_table(cut, tmp_path / "np" / "part-0.parquet")
    assert main(["--features", str(tmp_path / "np"), "--out", str(tmp_path / "n"), "--folds",
                 "2", "--quiet"]) == 0
    assert sorted(p.name for p in (tmp_path / "n").glob("*.joblib")) == [
        "mimo_classifier.joblib", "mimo_regressor.joblib"]
