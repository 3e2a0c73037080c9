"""lms-adapt end to end on tiny perception bags: an adapted pair the node loads (metric
schema and training settings checked as for shipped models), a manifest recording the
choice, the base and a domain profile of the user's frames, a model card; one frame works
and says how little it says; no data is a clean error."""

import numpy as np
import pytest
from lidar_quality_core.model_store import read_manifest
from lms_data import COLUMNS, perception_bags
from lidar_quality_training.lms import adapt
from lidar_quality_training.lms.dataset import build_dataset
from lms_ros.pipeline import LmsParameters, LmsSettings, default_model_paths, load_models

SETTINGS = LmsSettings(width=COLUMNS)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return perception_bags(tmp_path_factory.mktemp("lms_adapt") / "pb", n_sequences=3,
                           n_frames=2, seed=31)


@pytest.fixture(scope="module")
def ds(bags):
    # the CLI's settings (--width) give the same cache key: its runs read these rows
    return build_dataset(bags, SETTINGS, cache_dir=bags.parent / "cache", quiet=True)


def _args(bags, out, *more):
    return ["--data", str(bags), "--width", str(COLUMNS), "--out", str(out), "--cache",
            str(bags.parent / "cache"), "--quiet", *more]


def test_adapted_pair_loads_in_the_node_and_records_the_choice(bags, ds, tmp_path, capsys):
    out = tmp_path / "adapted"
    assert adapt.main(_args(bags, out)) == 0
    captured = capsys.readouterr()
    assert "chosen: confidence" in captured.out and "| recalibrate" in captured.out
    # the shipped models were made for 2048 columns: another geometry warns, never refuses
    assert "width" in captured.err
    cpath, rpath = out / "lms_classifier.joblib", out / "lms_regressor.joblib"
    warned = []
    params = LmsParameters(settings=SETTINGS, classifier_path=str(cpath),
                           regressor_path=str(rpath))
    models = load_models(params, warn=warned.append)   # the node's own loading and checks
    assert any("width" in w for w in warned)
    conf, iou = models.predict(ds.X)
    assert np.all((conf >= 0) & (conf <= 1)) and np.all((iou >= 0) & (iou <= 1))
    man = read_manifest(cpath)
    assert man["feature_names"] == list(SETTINGS.metric_names())
    td = man["training_data"]
    base = read_manifest(default_model_paths()[0])
    assert td["settings"] == base["training_data"]["settings"]
    assert td["adapted_from"]["model_id"] == base["model_id"]
    rec = td["adaptation"]
    assert rec["frames"] == 6 and rec["rows"] == len(ds) and rec["tp"] == int(ds.tp.sum())
    assert set(rec["chosen"]) == {"classification", "regression"}
    assert "grouped by sequence" in rec["scheme"]                # 3 bags = 3 sequences
    assert "detector score" not in rec["cross_validation"]       # the signal is mean_E
    assert models.domain_profile.quantities["mean_E"].count == len(ds)
    card = (out / "MODEL_CARD.md").read_text()
    assert "adapted" in card and str(bags) in card and "95 %" in card


def test_one_frame_and_no_data(bags, ds, tmp_path, capsys):
    out = tmp_path / "one"
    assert adapt.main(_args(bags, out, "--frames", "1")) == 0
    rec = read_manifest(out / "lms_classifier.joblib")["training_data"]["adaptation"]
    assert rec["frames"] == 1 and "one frame" in rec["scheme"]
    assert "uncertain" in (out / "MODEL_CARD.md").read_text()
    capsys.readouterr()
    assert adapt.main(["--out", str(tmp_path / "x")]) == 2
    assert "give the labelled data" in capsys.readouterr().err


def test_frames_alternate_between_sequences_and_key_the_rows(ds):
    picked = adapt.first_frames(ds, 4)
    assert len(picked) == 4 and len({k.rsplit("/", 1)[0] for k in picked}) == 3
    keys = adapt.frame_keys(ds)
    assert set(adapt.first_frames(ds, None)) == set(keys) and len(set(keys)) == ds.n_frames
    data = adapt.adapt_data(ds)
    assert data.signal == "mean_E" and data.transform == "identity"
    assert np.array_equal(data.tp, ds.tp) and np.array_equal(data.iou, ds.iou_adj)
    assert len(np.unique(data.sequence)) == 3
