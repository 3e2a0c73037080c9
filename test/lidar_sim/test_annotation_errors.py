"""Injected annotation errors are listed exactly as applied."""
import numpy as np
from lidar_sim.annotation_errors import (AnnotationErrorConfig, apply_records,
                                         inject_box_errors, inject_region_errors)

CONFUSIONS = {9: [10], 10: [9], 11: [12], 12: [11]}


def _gt(rng, m=200):
    boxes = np.column_stack([rng.uniform(-50, 50, (m, 2)), rng.uniform(-1, 0, m),
                             rng.uniform(1, 5, (m, 3)), rng.uniform(-3, 3, m)])
    return boxes, rng.choice([9, 10, 11, 12], m), np.arange(1, m + 1) * 3


def test_box_errors_diff_equals_records():
    rng = np.random.default_rng(11)
    boxes, classes, inst = _gt(rng)
    cfg = AnnotationErrorConfig(p_missing=0.1, p_shift=0.2, p_resize=0.2, p_wrong_class=0.2)
    records = inject_box_errors(boxes, classes, inst, CONFUSIONS, rng, cfg)
    kinds = {r["kind"] for r in records}
    assert kinds == {"missing", "shifted", "resized", "wrong_class"}
    a_boxes, a_classes, a_inst, _ = apply_records(records, boxes, classes, inst)
    # recompute the differences from clean vs annotated and compare with the records
    missing = set(inst.tolist()) - set(a_inst.tolist())
    assert missing == {r["instance"] for r in records if r["kind"] == "missing"}
    by_inst = {int(k): i for i, k in enumerate(inst)}
    changed_class, moved, scaled = set(), set(), set()
    for j, k in enumerate(a_inst.tolist()):
        i = by_inst[k]
        if a_classes[j] != classes[i]:
            changed_class.add(k)
            assert CONFUSIONS[int(classes[i])].count(int(a_classes[j])) == 1
        if not np.allclose(a_boxes[j, :2], boxes[i, :2]):
            moved.add(k)
        if not np.allclose(a_boxes[j, 3:6], boxes[i, 3:6]):
            scaled.add(k)
        np.testing.assert_array_equal(a_boxes[j, [2, 6]], boxes[i, [2, 6]])
    assert changed_class == {r["instance"] for r in records if r["kind"] == "wrong_class"}
    assert moved == {r["instance"] for r in records if r["kind"] == "shifted"}
    assert scaled == {r["instance"] for r in records if r["kind"] == "resized"}
    assert not missing & (changed_class | moved | scaled)


def test_no_errors_when_disabled():
    rng = np.random.default_rng(2)
    boxes, classes, inst = _gt(rng)
    cfg = AnnotationErrorConfig(p_missing=0, p_shift=0, p_resize=0, p_wrong_class=0,
                                regions_per_frame=0)
    assert inject_box_errors(boxes, classes, inst, CONFUSIONS, rng, cfg) == []
    assert inject_region_errors(boxes[:, :3], classes, [1, 2], rng, cfg) == []


def test_region_errors_relabel_exactly_the_listed_points():
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-20, 20, (5000, 3))
    labels = rng.choice([1, 2, 3], 5000)
    cfg = AnnotationErrorConfig(regions_per_frame=4, region_radius=(2.0, 4.0))
    records = inject_region_errors(xyz, labels, [1, 2, 3], rng, cfg)
    assert records and all(r["kind"] == "mislabeled_region" for r in records)
    *_, annotated = apply_records(records, np.zeros((0, 7)), [], [], xyz, labels)
    changed = annotated != labels
    inside_any = np.zeros(len(xyz), bool)
    for r in records:
        inside = np.linalg.norm(xyz - r["centre"], axis=1) <= r["radius"]
        assert inside.sum() == r["points"] > 0
        inside_any |= inside
    assert not changed[~inside_any].any()  # nothing outside the listed regions changed
    last = records[-1]  # the last region's points all carry its class
    inside = np.linalg.norm(xyz - last["centre"], axis=1) <= last["radius"]
    assert (annotated[inside] == last["to_class"]).all()
