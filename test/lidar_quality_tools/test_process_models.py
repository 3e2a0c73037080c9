"""process_bag checks the meta models' recorded training settings as the nodes do (issue
14, defect 6): the shipped threshold-mode models with ``proposal_mode=exact`` are refused
(exit 2, the setting and both values named, nothing written); another threshold warns."""
import pytest
from lmd_bags import write_bag
from lmd_ros.pipeline import default_model_paths
from lidar_quality_tools.process import main


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("process_models") / "seq_00"
    write_bag(path, [7])
    return path


def _threshold_models(monkeypatch):
    monkeypatch.delenv("LQ_MODELS_DIR", raising=False)
    c, r = default_model_paths("threshold")
    return ["--param", f"lmd.classifier_path={c}", "--param", f"lmd.regressor_path={r}"]


def test_models_of_another_mode_are_refused(bag, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        main(["--bag", str(bag), "--out", str(out), "--nodes", "lmd", "--no-progress",
              "--param", "lmd.proposal_mode=exact", *_threshold_models(monkeypatch)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "proposal_mode: model trained with 'threshold', node set to 'exact'" in err
    assert not out.exists()


def test_another_threshold_warns_and_runs(bag, tmp_path, capsys, monkeypatch):
    assert main(["--bag", str(bag), "--out", str(tmp_path / "out"), "--nodes", "lmd",
                 "--no-progress", "--param", "lmd.iou_threshold=0.4",
                 *_threshold_models(monkeypatch)]) == 0
    err = capsys.readouterr().err
    assert ("process_bag: lmd: warning: lmd_threshold_classifier.joblib, "
            "lmd_threshold_regressor.joblib: iou_threshold: model trained with 0.5, node "
            "set to 0.4") in err
