"""mimo_node checks its models' recorded training settings at start (issue 14, defect 6):
the other pair (``use_points``) or another class list is refused with the setting, both
values and the fix (node construction raises, the executable exits 2); other merge
settings only warn; the shipped models load with the shipped config.

The models are real: XGBoost fitted on merged clusters of synthetic multi-head frames
(``mimo_data.train_node_models``), their settings recorded as ``mimo-train`` records
them."""
import subprocess

import pytest
from lidar_quality_ros.params import config_parameters
from mimo_data import head_frames, train_node_models
from mimo_ros.mimo_node import MimoNode
from mimo_ros.pipeline import DEFAULT_CLASS_NAMES, MimoSettings
from node_shell_checks import executable


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """{use_points: (classifier, regressor)}."""
    root = tmp_path_factory.mktemp("mimo_setting_models")
    frames = head_frames(6)
    return {p: train_node_models(root, MimoSettings(use_points=p), frames)
            for p in (False, True)}


def params(paths, **extra):
    return {"classifier_path": str(paths[0]), "regressor_path": str(paths[1]), **extra}


def test_statistics_pair_with_use_points_is_refused(ros, models):
    with pytest.raises(RuntimeError) as e:
        ros.start(MimoNode, parameters=params(models[False], use_points=True))
    text = str(e.value)
    assert "mimo_classifier.joblib" in text
    assert "use_points: model trained with false, node set to true" in text
    assert "fix: set use_points to false" in text


def test_swapped_class_list_is_refused(ros, models):
    names = ["truck", "car", "pedestrian", "cyclist"]
    with pytest.raises(RuntimeError) as e:
        ros.start(MimoNode, parameters=params(models[False], class_names=names))
    text = str(e.value)
    assert (f"class_names: model trained with {list(DEFAULT_CLASS_NAMES)}, node set to "
            f"{names}".replace("'", '"') in text), text


def test_other_merge_settings_warn_and_run(ros, models, capfd):
    node = ros.start(MimoNode, parameters=params(models[True], use_points=True,
                                                 voting="affirmative", eps=0.6))
    found = "\n".join(node.models.warnings)
    assert len(node.models.warnings) == 2, found
    assert "voting: model trained with 'consensus', node set to 'affirmative'" in found
    assert "eps: model trained with 0.5, node set to 0.6" in found
    assert "voting: model trained with 'consensus'" in capfd.readouterr().err


def test_executable_exits_2_naming_the_setting(ros, models):
    c, r = models[False]
    proc = ros.spawn([str(executable("mimo_ros", "mimo_node")), "--ros-args",
                      "-p", "class_names:=[truck, car, pedestrian, cyclist]",
                      "-p", f"classifier_path:={c}", "-p", f"regressor_path:={r}"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2, out
    assert "node failed to start" in out and "class_names: model trained with" in out, out
    assert "Traceback" not in out, out


@pytest.mark.parametrize("use_points", [False, True])
def test_shipped_models_load_with_the_shipped_config(ros, monkeypatch, use_points):
    monkeypatch.delenv("LQ_MODELS_DIR", raising=False)
    p = {**config_parameters("mimo_ros", "mimo_node"), "use_points": use_points}
    node = ros.start(MimoNode, parameters=p)
    prefix = "mimo_points" if use_points else "mimo"
    assert node.models.confidence_model_id.startswith(f"{prefix}_classifier")
    assert node.models.warnings == []
