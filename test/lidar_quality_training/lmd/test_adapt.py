"""lmd-adapt end to end on tiny perception bags: an adapted pair the node loads (schema and
training settings checked as for shipped models), a manifest recording the choice, the
base and a domain profile of the user's frames, a model card; one frame works and says how
little it says; no data is a clean error."""

import numpy as np
import pytest
from lidar_quality_core.model_store import read_manifest
from lmd_bags import write_split
from lidar_quality_training.lmd import adapt
from lidar_quality_training.lmd import dataset as D
from lmd_ros.pipeline import LmdParameters, LmdSettings, default_model_paths, load_models


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("lmd_adapt")
    write_split(root / "user", 3, 2, seed0=700)
    return root


def test_adapted_pair_loads_in_the_node_and_records_the_choice(bags, tmp_path, capsys):
    out = tmp_path / "adapted"
    assert adapt.main(["--train", str(bags / "user"), "--mode", "none", "--out", str(out),
                       "--cache", "", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "chosen: confidence" in printed and "| detector score |" in printed
    cpath, rpath = out / "lmd_none_classifier.joblib", out / "lmd_none_regressor.joblib"
    s = LmdSettings(proposal_mode="none")
    params = LmdParameters(settings=s, classifier_path=str(cpath), regressor_path=str(rpath))
    models = load_models(params)                       # the node's own loading and checks
    ds = D.load_bags([bags / "user"], [D.settings_for("none")], progress=False)["none"]
    conf, iou = models.predict(ds.X)
    assert np.all((conf >= 0) & (conf <= 1)) and np.all((iou >= 0) & (iou <= 1))
    man = read_manifest(cpath)
    td = man["training_data"]
    base = read_manifest(default_model_paths("none")[0])
    assert td["settings"] == base["training_data"]["settings"]
    assert td["adapted_from"]["model_id"] == base["model_id"]
    rec = td["adaptation"]
    assert rec["frames"] == 6 and rec["rows"] == len(ds) and rec["tp"] == int(ds.tp.sum())
    assert set(rec["chosen"]) == {"classification", "regression"}
    assert "grouped by sequence" in rec["scheme"]                # 3 bags = 3 sequences
    assert models.domain_profile.quantities["detector score"].count == len(ds)
    card = (out / "MODEL_CARD.md").read_text()
    assert "adapted" in card and str(bags / "user") in card and "95 %" in card


def test_one_frame_and_no_data(bags, tmp_path, capsys):
    out = tmp_path / "one"
    assert adapt.main(["--train", str(bags / "user"), "--mode", "none", "--out", str(out),
                       "--frames", "1", "--cache", "", "--quiet"]) == 0
    rec = read_manifest(out / "lmd_none_classifier.joblib")["training_data"]["adaptation"]
    assert rec["frames"] == 1 and "one frame" in rec["scheme"]
    assert "uncertain" in (out / "MODEL_CARD.md").read_text()
    capsys.readouterr()
    assert adapt.main(["--mode", "none", "--out", str(tmp_path / "x")]) == 2
    assert "give the labelled data" in capsys.readouterr().err


def test_first_frames_alternate_between_sequences(bags):
    ds = D.load_bags([bags / "user"], [D.settings_for("none")], progress=False)["none"]
    picked = adapt.first_frames(ds, 3)
    assert len(set(ds.frame_group[picked].tolist())) == 3
    assert adapt.first_frames(ds, None).tolist() == list(range(ds.n_frames))


def test_real_kitti_scans_behind_the_reference_detector(tmp_path, capsys):
    """Real labelled KITTI scans (skipped without them): three frames, so only the
    few-coefficient candidates can be chosen, each with its interval; the pair loads."""
    from realdata import require_realdata_kitti
    from reference_perception.cli import main as perception_main

    root = require_realdata_kitti()
    res = tmp_path / "results"
    assert perception_main(["kitti", "--root", str(root), "--out", str(res), "--heads", "0",
                            "--no-segmenter", "--quiet"]) == 0
    out = tmp_path / "adapted"
    assert adapt.main(["--kitti-root", str(root), "--kitti-results", str(res), "--mode", "none",
                       "--kitti-group-digits", "0", "--out", str(out), "--cache", "",
                       "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "grouped by frame (3 frames)" in captured.out
    assert "tree candidates need 5 frames" in captured.err
    rec = read_manifest(out / "lmd_none_classifier.joblib")["training_data"]["adaptation"]
    assert set(rec["chosen"].values()) <= {"shipped", "score", "recalibrate"}
    lo, hi = rec["cross_validation"]["shipped"]["ci95"]["auroc"]
    assert hi - lo > 0.02                    # three scans: a wide interval, and it says so
    s = LmdSettings(proposal_mode="none")
    load_models(LmdParameters(settings=s, classifier_path=str(out / "lmd_none_classifier.joblib"),
                              regressor_path=str(out / "lmd_none_regressor.joblib")))
