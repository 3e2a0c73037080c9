"""lms_node checks its models' recorded training settings at start (issue 14, defect 6):
another class map or min_segment_points is refused with the setting, both values and the
fix (node construction raises, the executable exits 2); another image geometry (issue 16:
a sensor preset on models of another sensor) or ``sum_tolerance`` only warns, the geometry
also as the /diagnostics value ``model.geometry``; the shipped models load with the
shipped config.

The models are real: XGBoost fitted on small simulated scans with noisy probabilities
(``lms_data.train_node_models``), their settings recorded as ``lms-train`` records them."""
import subprocess

import pytest
from lidar_quality_ros.params import config_parameters
from lms_data import train_node_models
from lms_ros.lms_node import LmsNode
from lms_ros.pipeline import CLASS_NAMES
from lms_scans import node_parameters, scans, settings
from node_shell_checks import diag_values, executable


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return train_node_models(tmp_path_factory.mktemp("lms_setting_models"), scans(3, 1),
                             settings())


def params(paths, **extra):
    return node_parameters(classifier_path=str(paths[0]), regressor_path=str(paths[1]),
                           **extra)


def test_other_image_geometry_warns_and_shows_in_diagnostics(ros, models, capfd):
    # the metrics keep their names for any image size: only the settings tell
    node = ros.start(LmsNode, parameters=params(models, width=512))
    text = " ".join(node.models.warnings)
    assert "width: model trained with 256, node set to 512" in text
    assert "set width to 256 if that is your sensor's image" in text
    assert "width: model trained with 256" in capfd.readouterr().err
    values = diag_values(node.diag.status())
    assert values["model.geometry"] == ("trained 64 x 256, fov 3 .. -25 deg; running "
                                        "64 x 512, fov 3 .. -25 deg")
    assert values["image"] == "custom: 64 x 512"


def test_sensor_preset_runs_on_models_of_another_geometry(ros, models):
    node = ros.start(LmsNode, parameters=params(models, sensor="VLP-16"))
    assert (node.settings.channels, node.settings.width) == (16, 1800)
    values = diag_values(node.diag.status())
    assert values["image"] == "VLP-16: 16 x 1800"
    assert values["model.geometry"].startswith("trained 64 x 256")
    assert any("channels: model trained with 64, node set to 16" in w
               for w in node.models.warnings)


def test_other_min_segment_points_is_refused(ros, models):
    with pytest.raises(RuntimeError) as e:
        ros.start(LmsNode, parameters=params(models, min_segment_points=5))
    text = str(e.value)
    assert "lms_classifier.joblib" in text
    assert "min_segment_points: model trained with 10, node set to 5" in text


def test_swapped_class_map_is_refused(ros, models):
    names = list(CLASS_NAMES)
    names[10], names[11] = names[11], names[10]  # car <-> truck
    with pytest.raises(RuntimeError) as e:
        ros.start(LmsNode, parameters=params(models, class_names=names))
    text = str(e.value)
    assert "class_names: model trained with" in text and '"car", "truck"' in text
    assert f'node set to {names}'.replace("'", '"') in text, text


def test_other_sum_tolerance_warns_and_runs(ros, models, capfd):
    node = ros.start(LmsNode, parameters=params(models, sum_tolerance=0.05))
    assert len(node.models.warnings) == 1, node.models.warnings
    assert "sum_tolerance: model trained with 0.02, node set to 0.05" in node.models.warnings[0]
    assert "sum_tolerance: model trained with 0.02" in capfd.readouterr().err


def test_executable_exits_2_naming_the_setting(ros, models):
    c, r = models
    proc = ros.spawn([str(executable("lms_ros", "lms_node")), "--ros-args",
                      "-p", "min_segment_points:=5", "-p", "ring_zero_top:=true",
                      "-p", f"classifier_path:={c}", "-p", f"regressor_path:={r}"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2, out
    assert "node failed to start" in out and "min_segment_points: model trained with 10" in out, out
    assert "Traceback" not in out, out


def test_shipped_models_load_with_the_shipped_config(ros, monkeypatch):
    monkeypatch.delenv("LQ_MODELS_DIR", raising=False)
    node = ros.start(LmsNode, parameters=config_parameters("lms_ros", "lms_node"))
    assert node.models.confidence_model_id.startswith("lms_classifier")
    assert node.models.warnings == []
