"""mimo-adapt end to end on tiny perception bags: an adapted pair of either variant (with /
without point features) the node loads (schema and merge settings checked as for shipped
models), a manifest recording the choice, the base and a domain profile of the user's
frames, a model card; one frame works and says how little it says; no data is a clean
error."""

import numpy as np
import pytest
from lidar_quality_core.model_store import read_manifest
from mimo_data import perception_bags
from lidar_quality_training.mimo import adapt
from lidar_quality_training.mimo.dataset import load_bags
from mimo_ros.pipeline import MimoParameters, MimoSettings, default_model_paths, load_models


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return perception_bags(tmp_path_factory.mktemp("mimo_adapt"), n_sequences=3, n_frames=2,
                           seed=41)


@pytest.fixture(scope="module")
def ds(bags):
    return load_bags([bags], progress=False)


def _args(bags, out, *more):
    return ["--data", str(bags), "--out", str(out), "--cache", "", "--quiet", *more]


@pytest.mark.parametrize("use_points", [False, True])
def test_adapted_pair_loads_in_the_node_and_records_the_choice(bags, ds, tmp_path, capsys,
                                                               use_points):
    out = tmp_path / "adapted"
    flag = ["--use-points"] if use_points else []  # default: the node's use_points (off)
    assert adapt.main(_args(bags, out, *flag)) == 0
    printed = capsys.readouterr().out
    assert "chosen: confidence" in printed and "| detector score |" in printed
    prefix = "mimo_points" if use_points else "mimo"
    cpath, rpath = out / f"{prefix}_classifier.joblib", out / f"{prefix}_regressor.joblib"
    s = MimoSettings(use_points=use_points)
    warned = []
    params = MimoParameters(settings=s, classifier_path=str(cpath), regressor_path=str(rpath))
    models = load_models(params, warn=warned.append)    # the node's own loading and checks
    assert warned == []                                  # merge settings recorded and equal
    X, names = ds.features(use_points)
    assert read_manifest(cpath)["feature_names"] == list(names) == list(s.feature_names())
    conf, iou = models.predict(X)
    assert np.all((conf >= 0) & (conf <= 1)) and np.all((iou >= 0) & (iou <= 1))
    td = read_manifest(cpath)["training_data"]
    base = read_manifest(default_model_paths(use_points)[0])
    assert td["merge_settings"] == base["training_data"]["merge_settings"]
    assert td["merge_settings"]["use_points"] is use_points
    assert td["adapted_from"]["model_id"] == base["model_id"]
    rec = td["adaptation"]
    assert rec["frames"] == 6 and rec["rows"] == len(ds) and rec["tp"] == int(ds.tp.sum())
    assert set(rec["chosen"]) == {"classification", "regression"}
    assert "grouped by sequence" in rec["scheme"]                # 3 bags = 3 sequences
    assert models.domain_profile.quantities["detector score"].count == len(ds)
    card = (out / "MODEL_CARD.md").read_text()
    assert "adapted" in card and str(bags) in card and "95 %" in card


def test_one_frame_and_no_data(bags, tmp_path, capsys):
    out = tmp_path / "one"
    assert adapt.main(_args(bags, out, "--frames", "1")) == 0
    rec = read_manifest(out / "mimo_classifier.joblib")["training_data"]["adaptation"]
    assert rec["frames"] == 1 and "one frame" in rec["scheme"]
    assert "uncertain" in (out / "MODEL_CARD.md").read_text()
    capsys.readouterr()
    assert adapt.main(["--out", str(tmp_path / "x")]) == 2
    assert "give the labelled data" in capsys.readouterr().err


def test_frames_alternate_between_sequences(ds):
    picked = adapt.first_frames(ds, 3)
    assert len(set(ds.frame_group[picked].tolist())) == 3
    assert adapt.first_frames(ds, None).tolist() == list(range(ds.n_frames))
    data = adapt.adapt_data(ds, False)
    assert data.signal == "score" and data.transform == "logit"
    assert np.array_equal(data.tp, ds.m_iou_class >= 0.5)
    assert np.array_equal(data.X[:, data.column], ds.m_score)
