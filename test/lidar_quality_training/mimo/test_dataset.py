"""lidar_quality_training.mimo.dataset on tiny perception bags of the real reference multi-head detector."""
import numpy as np
import pytest
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.iou import iou_bev
from lidar_quality_core.pointcloud import read_fields
from lidar_quality_ros.bag_io import BagWriter, read_bag
from lidar_quality_ros.perception_bag import perception_frames
from lidar_quality_training.mimo.dataset import (EVAL_MAX_RANGE, EVAL_MIN_POINTS, TP_IOU, MimoDataset,
                                                load_bags, read_bag as read_mimo_bag)
from mimo_ros.pipeline import STAT_FEATURES, MimoSettings, frame_features, head_detections
from mimo_data import perception_bags


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return perception_bags(tmp_path_factory.mktemp("mimo_ds"), n_sequences=2, n_frames=3)


@pytest.fixture(scope="module")
def ds(bags):
    return load_bags([bags], progress=False)


def test_rows_are_the_pipeline_features_and_targets(bags, ds):
    assert ds.n_frames == 6 and ds.groups == ["bags/seq_00", "bags/seq_01"]
    assert len(ds) > 50 and len(ds.s_score) > 50
    frames = list(perception_frames(bags / "seq_01", want=("points", "points_gt", "gt_objects"),
                                    heads=2))
    f = frames[1]
    k = int(np.flatnonzero((ds.frame_group == "bags/seq_01")
                           & (ds.frame_stamp == f.stamp_ns))[0])
    rows = np.flatnonzero(ds.m_frame == k)
    # the node's own features, with and without the point features
    full = frame_features(f.heads, f.head_variances, MimoSettings(use_points=True), f.points)
    stat = frame_features(f.heads, f.head_variances, MimoSettings(), None)
    np.testing.assert_array_equal(ds.X[rows], full.features)
    np.testing.assert_array_equal(ds.features(False)[0][rows], stat.features)
    assert ds.features(False)[1] == STAT_FEATURES
    np.testing.assert_array_equal(ds.m_box[rows], full.merge.boxes)
    np.testing.assert_array_equal(ds.m_probs[rows], full.merge.class_probs)
    np.testing.assert_array_equal(ds.m_var[rows], full.merge.stats.predictive_variance)
    # targets: BEV IoU with the best GT box of the same class / of any class
    gt = detections_to_arrays(f.gt_objects)
    iou = iou_bev(full.merge.boxes, gt.boxes)
    names = np.array(ds.class_names)[full.merge.labels - 1]
    same = names[:, None] == np.array(gt.labels)[None, :]
    np.testing.assert_allclose(ds.m_iou_class[rows], np.where(same, iou, 0).max(axis=1))
    np.testing.assert_allclose(ds.m_iou_any[rows], iou.max(axis=1))
    assert np.array_equal(ds.tp[rows], ds.m_iou_class[rows] >= TP_IOU)
    assert 0 < ds.tp.mean() < 1
    # single head = head 0's usable boxes, score = its top hypothesis
    h, arr = head_detections(f.heads[0], f.head_variances[0], MimoSettings())
    srows = np.flatnonzero(ds.s_frame == k)
    np.testing.assert_array_equal(ds.s_box[srows], h.boxes)
    np.testing.assert_allclose(ds.s_score[srows], arr.scores)
    assert list(ds.labels("s")[srows]) == list(arr.labels)
    np.testing.assert_array_equal(ds.s_var[srows], h.variances)
    # ground truth and its point counts (instance labels of /lidar/points_gt)
    gb, gl, gi, gp = ds.gt_of(k)
    np.testing.assert_array_equal(gb, gt.boxes)
    inst = read_fields(f.points_gt, "instance", np.int64)[:, 0]
    assert gp.tolist() == [int((inst == int(i)).sum()) for i in gi]
    ign = ds.gt_ignore()
    r = np.hypot(ds.gt_box[:, 0], ds.gt_box[:, 1])
    assert np.array_equal(ign, (ds.gt_points < EVAL_MIN_POINTS) | (r > EVAL_MAX_RANGE))
    assert 0 < ign.sum() < len(ign)


def test_cache_roundtrip_subset_and_concat(bags, ds, tmp_path):
    a = load_bags([bags], cache_dir=tmp_path, progress=False)
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 2
    stamps = [p.stat().st_mtime_ns for p in files]
    b = load_bags([bags], cache_dir=tmp_path, progress=False)  # from the cache
    assert [p.stat().st_mtime_ns for p in files] == stamps
    for x in (a, b):
        for k in ("X", "m_probs", "m_iou_class", "s_score", "gt_box", "gt_offsets", "m_frame"):
            np.testing.assert_array_equal(getattr(x, k), getattr(ds, k))
        assert list(x.gt_label) == list(ds.gt_label)
    sub = ds.subset_frames(ds.frames_of_groups(["bags/seq_01"]))
    assert sub.n_frames == 3 and sub.groups == ["bags/seq_01"]
    keep = ds.frame_group[ds.m_frame] == "bags/seq_01"
    np.testing.assert_array_equal(sub.X, ds.X[keep])
    for k in range(sub.n_frames):
        np.testing.assert_array_equal(sub.gt_of(k)[0], ds.gt_of(k + 3)[0])
    first = ds.subset_frames(ds.frames_of_groups(["bags/seq_00"]))
    back = MimoDataset.concat([first, sub])
    np.testing.assert_array_equal(back.X, ds.X)
    np.testing.assert_array_equal(back.m_frame, ds.m_frame)
    np.testing.assert_array_equal(back.gt_offsets, ds.gt_offsets)


def test_a_bag_without_heads_is_refused(bags, tmp_path):
    dst = tmp_path / "no_heads"
    with BagWriter(dst) as w:
        for m in read_bag(bags / "seq_00"):
            if not m.topic.startswith("/perception/"):
                w.write(m.topic, m.msgtype, m.stamp_ns, m.raw)
    with pytest.raises(ValueError, match="head_0"):
        read_mimo_bag(dst, progress=False)


def test_topic_options_read_bags_under_other_names(bags, ds, tmp_path, capsys):
    """mimo-train / mimo-eval's --topic: bags under a user's own topic names (heads too)
    give the clusters of the same bags under the default names."""
    import argparse

    from lidar_quality_training.mimo.train import add_data_arguments
    from realbags import user_named_copy

    users = tmp_path / "users"
    for bag in sorted(bags.iterdir()):
        topic_args = user_named_copy(bag, users / bag.name)
    ap = argparse.ArgumentParser()
    add_data_arguments(ap, "unused")
    a = ap.parse_args(["--data", str(users), *topic_args])
    got = load_bags(a.data, progress=False, topics=dict(a.topic))
    assert len(got) == len(ds) > 0
    np.testing.assert_array_equal(got.X, ds.X)
    np.testing.assert_array_equal(got.m_iou_class, ds.m_iou_class)
    with pytest.raises(ValueError, match="no /perception/head_0 topic"):
        load_bags([users], progress=False)
    with pytest.raises(SystemExit):
        ap.parse_args(["--topic", "head=/x"])
    assert "unknown topic key 'head'" in capsys.readouterr().err
