"""LMS segment dataset: rows equal the metrics and targets of the raw arrays, both sources
(perception bags, SemanticKITTI-style directory), sub-sequence groups, cache."""
import dataclasses

import numpy as np
import pytest
from lidar_quality_core import meta_model
from lidar_quality_core.pointcloud import cloud_to_structured
from lidar_quality_ros.perception_bag import perception_frames
from lms_data import COLUMNS, perception_bags, semantickitti_dir
from lidar_quality_training.lms.dataset import (SegmentDataset, build_dataset, discover_sources, load_frame,
                             subsequence_groups)
from lms_ros.pipeline import LmsSettings
from lidar_quality_core.lms.segment_metrics import compute_segments
from lidar_quality_core.lms.targets import segment_targets

SETTINGS = LmsSettings(width=COLUMNS)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("lms_data")
    return {"bags": perception_bags(root / "pb", n_sequences=2, n_frames=4),
            "sk": semantickitti_dir(root / "sk", n_frames=3)}


def _direct_rows(xyz, probs, gt, ring=None, intensity=None, settings=SETTINGS, ignore=0):
    """Metrics and targets straight from the arrays (no messages, no pipeline)."""
    res = compute_segments(xyz, probs, settings.range_config(), ring=ring, intensity=intensity,
                           min_points=settings.min_segment_points,
                           class_names=settings.class_names)
    iou, adj = segment_targets(res, gt, ignore_label=ignore)
    ok = np.isfinite(adj)
    return res.features[ok], iou[ok], adj[ok], res.segment_class[res.kept_ids[ok]]


def test_bag_rows_are_the_metrics_of_the_recorded_arrays(data, tmp_path):
    # ring 0 = top in lidar_sim: with ring_zero_top the rows are the rings unflipped
    s = dataclasses.replace(SETTINGS, ring_zero_top=True)
    ds = build_dataset(data["bags"], s, block_frames=2, quiet=True)
    assert ds.names == s.metric_names() and ds.X.shape == (len(ds), 86 + 2 * 14)
    assert ds.sequences == ("bags/seq_00", "bags/seq_01") and ds.info["n_frames"] == 8
    rows = []
    for k, seq in enumerate(sorted(data["bags"].iterdir())):
        for f in perception_frames(seq, want=("points", "segmentation", "points_gt")):
            pts = cloud_to_structured(f.points)
            seg = cloud_to_structured(f.segmentation)
            xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1)
            probs = np.stack([seg[n] for n in s.field_names()], axis=1)
            if probs.dtype == np.uint8:   # the perception bags' default: round(p * 255)
                probs = probs.astype(np.float32) / np.float32(255)
            X, iou, adj, cls = _direct_rows(xyz, probs, cloud_to_structured(f.points_gt)["label"],
                                            ring=pts["ring"].astype(np.int32),
                                            intensity=pts["intensity"], settings=s)
            m = (ds.sequence == k) & (ds.frame == f.index)
            np.testing.assert_allclose(ds.X[m], X, rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(ds.iou_adj[m], adj)
            np.testing.assert_array_equal(ds.segment_class[m], cls)
            rows.append(len(adj))
    assert sum(rows) == len(ds) > 100
    assert ((ds.iou_adj >= 0) & (ds.iou_adj <= 1)).all() and (ds.iou <= ds.iou_adj + 1e-12).all()
    assert 0.05 < ds.tp.mean() < 0.95            # both kinds of segments occur
    assert (ds.size_projected >= s.min_segment_points).all() and (ds.size >= ds.size_projected).all()


def test_semantickitti_rows_and_ignore_label(data):
    from lidar_sim.classes import from_semantickitti

    (src,) = discover_sources(data["sk"])
    assert src.kind == "semantickitti" and src.name.endswith("/08")
    ignored = build_dataset(data["sk"], SETTINGS, block_frames=2, quiet=True)
    counted = build_dataset(data["sk"], SETTINGS, ignore_label=None, quiet=True)
    assert ignored.info["ignore_label"] == 0 and counted.info["ignore_label"] is None
    seq = src.path
    differs = False
    for i in range(3):
        pts = np.fromfile(seq / "velodyne" / f"{i:06d}.bin", "<f4").reshape(-1, 4)
        gt = from_semantickitti(np.fromfile(seq / "labels" / f"{i:06d}.label", "<u4"))
        assert (gt == 0).any()                   # the far points are unlabeled
        probs = np.load(seq / "probabilities" / f"{i:06d}.npy")
        for ds, ignore in ((ignored, 0), (counted, None)):
            X, iou, adj, _ = _direct_rows(pts[:, :3], probs, gt, intensity=pts[:, 3],
                                          ignore=ignore)
            m = ds.frame == i
            np.testing.assert_allclose(ds.X[m], X, rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(ds.iou_adj[m], adj)
        a, b = ignored.iou_adj[ignored.frame == i], counted.iou_adj[counted.frame == i]
        differs |= len(a) != len(b) or not np.array_equal(a, b)
    assert differs                               # unlabeled ground truth matters here
    assert counted.info["dropped_undefined"] == 0


def test_min_points_excludes_small_segments(data):
    small = build_dataset(data["sk"], SETTINGS, quiet=True)
    big = build_dataset(data["sk"], dataclasses.replace(SETTINGS, min_segment_points=40),
                        quiet=True)
    assert (big.size_projected >= 40).all() and 0 < len(big) < len(small)
    assert big.info["n_excluded"] > small.info["n_excluded"]


def test_subsequence_groups_keep_blocks_together():
    seq = np.repeat([0, 1], 40)
    frame = np.tile(np.arange(40), 2)
    g = subsequence_groups(seq, frame, 10)
    assert len(np.unique(g)) == 8
    for s in (0, 1):
        for b in range(4):
            m = (seq == s) & (frame // 10 == b)
            assert len(np.unique(g[m])) == 1     # a block is one group
    assert len(np.unique(g[frame // 10 == 0])) == 2   # same block index, other sequence
    fold = np.empty(len(g), int)
    for f, (_, va) in enumerate(meta_model.group_folds(g, 10, seed=3)):
        fold[va] = f
    # neighbouring frames of a block are always in the same fold
    for s in (0, 1):
        m = np.flatnonzero(seq == s)
        same_block = (frame[m][1:] // 10) == (frame[m][:-1] // 10)
        assert (fold[m][1:][same_block] == fold[m][:-1][same_block]).all()
    with pytest.raises(ValueError):
        subsequence_groups(seq, frame, 0)


def test_dataset_groups_cache_and_roundtrip(data, tmp_path):
    cache = tmp_path / "cache"
    ds = build_dataset(data["bags"], SETTINGS, block_frames=2, cache_dir=cache, quiet=True)
    files = sorted(cache.glob("*.npz"))
    assert len(files) == 2
    np.testing.assert_array_equal(ds.group, ds.sequence * 2 + ds.frame // 2)
    again = build_dataset(data["bags"], SETTINGS, block_frames=4, cache_dir=cache, quiet=True)
    assert sorted(cache.glob("*.npz")) == files    # read from the cache
    np.testing.assert_array_equal(again.X, ds.X)
    np.testing.assert_array_equal(again.group, ds.sequence)   # one block per sequence
    build_dataset(data["bags"], dataclasses.replace(SETTINGS, min_segment_points=20),
                  cache_dir=cache, quiet=True)
    assert len(list(cache.glob("*.npz"))) == 4      # other settings: other cache entries
    loaded = SegmentDataset.load(ds.save(tmp_path / "ds.npz"))
    for k in ("X", "iou", "iou_adj", "group", "frame", "sequence", "segment_class"):
        np.testing.assert_array_equal(getattr(loaded, k), getattr(ds, k))
    assert loaded.names == ds.names and loaded.info == ds.info
    sub = ds.subset(ds.tp)
    assert sub.tp.all() and len(sub) == ds.tp.sum()


def test_load_frame_and_bad_sources(data, tmp_path):
    src = discover_sources(data["bags"])[1]
    inp, gt, res, iou, adj = load_frame(src, 2, SETTINGS)
    assert len(gt) == len(inp.xyz) and len(adj) == len(res.kept_ids)
    with pytest.raises(IndexError):
        load_frame(src, 99, SETTINGS)
    with pytest.raises(FileNotFoundError):
        discover_sources(tmp_path)
    (tmp_path / "sequences" / "00" / "velodyne").mkdir(parents=True)
    (tmp_path / "sequences" / "00" / "labels").mkdir()
    with pytest.raises(FileNotFoundError, match="probabilities"):
        discover_sources(tmp_path)


def test_topic_options_read_bags_under_other_names(data, tmp_path):
    """lms-train / lms-eval's --topic: bags under a user's own topic names give the
    segments of the same bags under the default names."""
    import argparse

    from lidar_quality_training.lms.train import add_data_arguments, dataset_from_args
    from realbags import user_named_copy

    users = tmp_path / "users"
    for bag in sorted(data["bags"].iterdir()):
        topic_args = user_named_copy(bag, users / bag.name)
    ap = argparse.ArgumentParser()
    add_data_arguments(ap)
    ref = dataset_from_args(ap.parse_args(["--cache", "", "--quiet"]), [data["bags"]])
    got = dataset_from_args(ap.parse_args(["--cache", str(tmp_path / "c"), "--quiet",
                                           *topic_args]), [users])
    assert len(got) == len(ref) > 0
    np.testing.assert_array_equal(got.X, ref.X)
    np.testing.assert_array_equal(got.iou_adj, ref.iou_adj)
    with pytest.raises(ValueError, match="no topic /perception/segmentation"):
        dataset_from_args(ap.parse_args(["--cache", "", "--quiet"]), [users])
