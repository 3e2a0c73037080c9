"""autoware_objects: DetectedObjects read into DetectionArrays (boxes, classes, shapes) as
the vision_msgs path reads the same scene, and the meta confidence written back."""
import numpy as np
import pytest
from autoware_scenes import hand_built_scene as _scene
from lidar_quality_core.autoware_objects import (label_names, objects_to_arrays,
                                                 parse_class_map, score_objects)
from lidar_quality_core.boxes import arrays_to_detections, detections_to_arrays
from std_msgs.msg import Header


def test_boxes_classes_and_shapes():
    a = objects_to_arrays(_scene())
    assert a.ids == ["0", "1", "2", "3", "4"]
    np.testing.assert_allclose(a.boxes[0], [10, 2, 0.8, 4.2, 1.8, 1.5, 0.3], atol=1e-6)
    np.testing.assert_allclose(a.boxes[1, 3:6], [0.6, 0.6, 1.7], atol=1e-6)  # cylinder
    np.testing.assert_allclose(a.boxes[2, 3:6], [1.8, 0.6, 1.2], atol=1e-6)  # polygon extents
    assert a.labels[:4] == ["car", "pedestrian", "cyclist", "bus"]  # BUS: no model class
    np.testing.assert_allclose(a.scores[:4], [0.75, 0.5, 0.625, 0.875])
    np.testing.assert_allclose(a.class_scores["truck"][0], 0.25)
    assert a.valid.tolist() == [True, True, True, True, False]
    assert a.reasons[4] == "unknown shape type 7"


def test_same_arrays_as_the_vision_msgs_path():
    # the scene's first three objects as Detection3DArray, read by the vision_msgs rules
    aw = objects_to_arrays(_scene())
    boxes = aw.boxes[:3]
    vis = detections_to_arrays(arrays_to_detections(
        Header(frame_id="base_link"), boxes, aw.labels[:3], aw.scores[:3], ids=aw.ids[:3]))
    np.testing.assert_allclose(vis.boxes, boxes, atol=1e-6)
    assert vis.labels == aw.labels[:3] and vis.ids == aw.ids[:3]
    np.testing.assert_allclose(vis.scores, aw.scores[:3])


def test_class_map_parameter():
    m = parse_class_map("CAR:car, BUS:truck trailer:truck")
    assert m == {"CAR": "car", "BUS": "truck", "TRAILER": "truck"}
    assert label_names(m)[3] == "truck" and label_names(m)[7] == "pedestrian"
    assert objects_to_arrays(_scene(), m).labels[3] == "truck"
    with pytest.raises(ValueError, match="not an Autoware label"):
        parse_class_map("LORRY:truck")
    with pytest.raises(ValueError, match="expected AUTOWARE_LABEL:class_name"):
        parse_class_map("CAR")


def test_scores_written_back_and_nan_never_out():
    msg = _scene()
    msg.objects[3].existence_probability = float("nan")
    n = score_objects(msg, [0.9, 0.2, np.nan, np.nan, 0.4])
    assert n == 2
    e = [o.existence_probability for o in msg.objects]
    np.testing.assert_allclose(e, [0.9, 0.2, 0.5, 0.0, 0.4], rtol=1e-6)  # float32 fields
    car = [c.probability for c in msg.objects[0].classification]
    np.testing.assert_allclose(car, [0.9, 0.3], rtol=1e-6)  # top = confidence, ratio kept
    assert msg.objects[2].classification[0].probability == 0.625  # unscored: as it came
    fixed = _scene()
    assert score_objects(fixed, [np.nan] * 5, fallback=0.1) == 5
    assert all(abs(o.existence_probability - 0.1) < 1e-7 for o in fixed.objects)
    with pytest.raises(ValueError, match="2 confidences for 5 objects"):
        score_objects(_scene(), [0.1, 0.2])


def test_objects_from_new_boxes():
    from lidar_quality_core.autoware_objects import objects_from_boxes
    boxes = np.array([[1, 2, 0.5, 4, 2, 1.5, 0.4], [5, -1, 0.4, 0.8, 0.7, 1.8, -2.0]])
    probs = np.array([[0.6, 0.1, 0.05], [0.05, 0.3, 0.5]])  # car, bus-like "van", pedestrian
    var = np.array([[0.1, 0.2, 0.05, 0.01], [np.nan, 0.1, 0.1, 0.02]])
    msg, n = objects_from_boxes(Header(frame_id="base_link"), boxes, ["car", "van", "pedestrian"],
                                probs, [0.9, np.nan], fallback=[0.6, 0.5], variance=var)
    assert n == 1 and msg.header.frame_id == "base_link"
    a, b = msg.objects
    np.testing.assert_allclose([a.existence_probability, b.existence_probability], [0.9, 0.5],
                               rtol=1e-6)
    # highest first; "van" has no Autoware label: UNKNOWN (0)
    assert [c.label for c in a.classification] == [1, 0, 7]
    assert [c.label for c in b.classification] == [7, 0, 1]
    k = a.kinematics
    np.testing.assert_allclose(np.asarray(k.pose_with_covariance.covariance)[[0, 7, 14, 35]],
                               var[0])
    assert k.has_position_covariance and not b.kinematics.has_position_covariance
    assert k.orientation_availability == k.SIGN_UNKNOWN
    back = objects_to_arrays(msg)
    np.testing.assert_allclose(back.boxes, boxes, atol=1e-9)
