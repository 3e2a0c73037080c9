"""lmd_node checks its models' recorded training settings at start (issue 14, defect 6):
another proposal mode or class list is refused with the setting, both values and the fix
(node construction raises, the executable exits 2); another threshold of the mode in use
only warns; a model without recorded settings loads with a warning; the shipped models
load with the shipped config.

The models are real: XGBoost fitted on synthetic frames (``lmd_frames.train_models``)
with their settings recorded as ``lmd-train`` records them."""
import subprocess

import pytest
from lidar_quality_ros.params import config_parameters
from lmd_frames import train_models
from lmd_ros.lmd_node import LmdNode
from lmd_ros.pipeline import LmdSettings
from node_shell_checks import executable

CLASSES = ["car", "truck", "pedestrian", "cyclist"]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """{"recorded" | "older": (classifier, regressor)} of threshold-mode models, with
    and without the training settings in their manifests."""
    root = tmp_path_factory.mktemp("lmd_setting_models")
    return {"recorded": train_models(root / "recorded", LmdSettings(), record_settings=True),
            "older": train_models(root / "older", LmdSettings())}


def params(paths, **extra):
    return {"classifier_path": str(paths[0]), "regressor_path": str(paths[1]), **extra}


def test_threshold_models_in_exact_mode_are_refused(ros, models):
    # exact and threshold share the 90-feature schema: only the settings tell them apart
    with pytest.raises(RuntimeError) as e:
        ros.start(LmdNode, parameters=params(models["recorded"], proposal_mode="exact"))
    text = str(e.value)
    assert "lmd_threshold_classifier.joblib" in text
    assert "proposal_mode: model trained with 'threshold', node set to 'exact'" in text
    assert "fix: set proposal_mode to 'threshold'" in text


@pytest.mark.parametrize("names", [CLASSES[:3], ["truck", "car", "pedestrian", "cyclist"]],
                         ids=["three_classes", "swapped"])
def test_other_class_list_is_refused(ros, models, names):
    with pytest.raises(RuntimeError) as e:
        ros.start(LmdNode, parameters=params(models["recorded"], class_names=names))
    text = str(e.value)
    assert (f"class_names: model trained with {CLASSES}, node set to {names}"
            .replace("'", '"') in text), text
    assert "the class feature is the position in this list" in text


def test_other_threshold_of_the_mode_warns_and_runs(ros, models, capfd):
    node = ros.start(LmdNode, parameters=params(models["recorded"], iou_threshold=0.4,
                                                nms_iou_threshold=0.3))
    # nms_iou_threshold belongs to exact mode: not a finding in threshold mode
    assert len(node.models.warnings) == 1, node.models.warnings
    warning = node.models.warnings[0]
    assert "iou_threshold: model trained with 0.5, node set to 0.4" in warning
    assert "lmd-train --iou-threshold 0.4" in warning
    assert "iou_threshold: model trained with 0.5, node set to 0.4" in capfd.readouterr().err


def test_model_without_recorded_settings_warns_and_runs(ros, models, capfd):
    node = ros.start(LmdNode, parameters=params(models["older"]))
    assert len(node.models.warnings) == 1
    assert "cannot check proposal_mode, class_names" in node.models.warnings[0]
    assert "records no training settings" in capfd.readouterr().err


def test_executable_exits_2_naming_the_setting(ros, models):
    c, r = models["recorded"]
    proc = ros.spawn([str(executable("lmd_ros", "lmd_node")), "--ros-args",
                      "-p", "proposal_mode:=exact", "-p", f"classifier_path:={c}",
                      "-p", f"regressor_path:={r}"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2, out
    assert "node failed to start" in out, out
    assert "proposal_mode: model trained with 'threshold', node set to 'exact'" in out, out
    assert "Traceback" not in out, out


@pytest.mark.parametrize("mode", ["threshold", "exact", "none"])
def test_shipped_models_load_with_the_shipped_config(ros, monkeypatch, mode):
    monkeypatch.delenv("LQ_MODELS_DIR", raising=False)
    p = {**config_parameters("lmd_ros", "lmd_node"), "proposal_mode": mode}
    node = ros.start(LmdNode, parameters=p)
    assert node.models.confidence_model_id.startswith(f"lmd_{mode}_classifier")
    assert node.models.warnings == []
