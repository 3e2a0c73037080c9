"""lidar_quality_training.lmd.dataset: rows from perception bags and KITTI directories equal the pipeline's
features of the same messages, targets equal an independent IoU computation, the cache is
keyed by inputs and settings, KITTI boxes survive the file round trip."""
import os

import numpy as np
import pytest
from lidar_quality_core import synthetic
from lidar_quality_core.iou import iou_bev
from lidar_sim import kitti
from lmd_bags import write_bag, write_split
from lmd_frames import CLASS_NAMES
from lidar_quality_training.lmd import dataset as D
from lmd_ros.pipeline import frame_features

MODES = ("exact", "threshold", "none")


def settings():
    return [D.settings_for(m) for m in MODES]


def points_inside(points, boxes):
    """Brute force: points of each box (boundary inclusive) in the box frame."""
    out = []
    for b in boxes:
        d = points.astype(float) - b[:3]
        c, s = np.cos(-b[6]), np.sin(-b[6])
        lx, ly = c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]
        out.append(int(((np.abs(lx) <= b[3] / 2) & (np.abs(ly) <= b[4] / 2)
                        & (np.abs(d[:, 2]) <= b[5] / 2)).sum()))
    return np.array(out)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    frames = write_bag(root / "seq_07", [11, 12])
    return root / "seq_07", frames


def test_bag_rows_equal_pipeline_features_and_targets(bag, tmp_path):
    path, frames = bag
    data = D.load_bags([path], settings(), cache_dir=tmp_path, progress=False)
    assert set(data) == set(MODES)
    for s in settings():
        ds = data[s.proposal_mode]
        assert ds.feature_names == s.feature_names() and ds.n_frames == 2
        assert ds.groups == [f"{path.parent.name}/seq_07"]
        for k, (f, (cloud, dets, props, gt), stamp) in enumerate(frames):
            fr = frame_features(cloud, None if s.proposal_mode == "exact" else dets,
                                None if s.proposal_mode == "none" else props, s)
            rows = np.flatnonzero(ds.frame == k)
            valid = np.flatnonzero(fr.valid)
            assert len(rows) == len(valid) > 5
            np.testing.assert_array_equal(ds.X[rows], fr.features[valid])
            np.testing.assert_array_equal(ds.det_index[rows], valid)
            np.testing.assert_array_equal(ds.box[rows], fr.detections.boxes[valid])
            np.testing.assert_array_equal(ds.score[rows], fr.detections.scores[valid])
            assert ds.label[rows].tolist() == [fr.detections.labels[i] for i in valid]
            assert ds.frame_key[k] == str(stamp)
            # targets, independently: best BEV IoU over all GT boxes / same-class boxes
            iou = iou_bev(ds.box[rows], f.gt_boxes)
            np.testing.assert_allclose(ds.iou_any[rows], iou.max(axis=1), atol=1e-12)
            gt_names = np.array([synthetic.CLASS_NAMES[c] for c in f.gt_classes])
            same = ds.label[rows][:, None] == gt_names[None, :]
            np.testing.assert_allclose(ds.iou_class[rows], np.where(same, iou, 0).max(axis=1),
                                       atol=1e-12)
            boxes, labels, ids = ds.gt_of(k)
            np.testing.assert_allclose(boxes, f.gt_boxes, atol=1e-12)
            assert labels.tolist() == gt_names.tolist()
            a, b = ds.gt_offsets[k], ds.gt_offsets[k + 1]
            np.testing.assert_array_equal(ds.gt_points[a:b], points_inside(f.points, f.gt_boxes))
        np.testing.assert_array_equal(ds.tp, ds.iou_any >= 0.5)
        assert 0 < ds.tp.sum() < len(ds)  # noisy copies (TP) and background proposals (FP)
        aware = ds.with_class_aware(True)
        np.testing.assert_array_equal(aware.tp, ds.iou_class >= 0.5)


def test_cache_is_used_and_keyed_by_settings_and_inputs(tmp_path):
    bag = tmp_path / "bags" / "seq_00"
    write_bag(bag, [3])
    cache = tmp_path / "cache"
    first = D.load_bags([bag], [D.settings_for("threshold")], cache_dir=cache,
                        progress=False)["threshold"]
    files = sorted(cache.glob("*.npz"))
    assert len(files) == 1
    # A doctored cache file is what comes back: the bag is not read again.
    doctored = D.LmdDataset.load(files[0])
    doctored.score = doctored.score * 0 + 0.123
    doctored.save(files[0])
    again = D.load_bags([bag], [D.settings_for("threshold")], cache_dir=cache,
                        progress=False)["threshold"]
    assert np.all(again.score == 0.123)
    # Other settings, or a changed bag file, build anew.
    other = D.load_bags([bag], [D.settings_for("threshold", iou_threshold=0.3)],
                        cache_dir=cache, progress=False)["threshold"]
    np.testing.assert_array_equal(other.score, first.score)
    assert other.info["settings"]["iou_threshold"] == 0.3
    assert len(list(cache.glob("*.npz"))) == 2
    mcap = next(bag.glob("*.mcap"))
    st = mcap.stat()
    os.utime(mcap, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    fresh = D.load_bags([bag], [D.settings_for("threshold")], cache_dir=cache,
                        progress=False)["threshold"]
    np.testing.assert_array_equal(fresh.score, first.score)
    assert len(list(cache.glob("*.npz"))) == 3


def test_split_directories_concat_and_roundtrip(tmp_path):
    write_split(tmp_path / "split", 2, 1, seed0=40)
    bags = D.resolve_bags([tmp_path / "split"])
    assert [b.name for b in bags] == ["seq_00", "seq_01"]
    ds = D.load_bags([tmp_path / "split"], [D.settings_for("none")], cache_dir=None,
                     progress=False)["none"]
    parts = [D.load_bags([b], [D.settings_for("none")], progress=False)["none"] for b in bags]
    assert ds.groups == ["split/seq_00", "split/seq_01"] and ds.n_frames == 2
    assert len(ds) == sum(len(p) for p in parts)
    np.testing.assert_array_equal(ds.frame[len(parts[0]):], parts[1].frame + 1)
    for k, p in enumerate(parts):
        np.testing.assert_array_equal(ds.gt_of(k)[0], p.gt_of(0)[0])
    path = ds.save(tmp_path / "ds.npz")
    back = D.LmdDataset.load(path)
    for name in D._ROW + D._FRAME:
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name))
    assert back.feature_names == ds.feature_names and back.info == ds.info
    with pytest.raises(FileNotFoundError, match="not a rosbag2"):
        D.resolve_bags([tmp_path / "split" / "seq_00" / "nothing"])


# ------------------------------------------------------------------------------ KITTI
def write_kitti(root, frames):
    """KITTI dataset + result files + proposal files of synthetic frames."""
    results, proposals = root / "results", root / "proposals"
    results.mkdir(parents=True)
    proposals.mkdir()
    kitti_type = {"car": "Car", "pedestrian": "Pedestrian", "cyclist": "Cyclist"}
    for fid, f in frames.items():
        types = [kitti_type[synthetic.CLASS_NAMES[c]] for c in f.gt_classes]
        kitti.write_frame(root, fid, f.points, f.intensity, f.gt_boxes, types,
                          np.zeros(len(f.gt_boxes)), calib=kitti.SIM_CALIB)
        bg = np.flatnonzero(f.prop_object < 0)[:4]
        det_boxes = np.concatenate([f.detections, f.proposals[bg]])
        det_types = [kitti_type[synthetic.CLASS_NAMES[c]]
                     for c in np.concatenate([f.det_classes, f.prop_classes[bg]])]
        det_scores = np.concatenate([f.det_scores, f.prop_scores[bg]])
        (results / f"{fid}.txt").write_text("".join(
            line + "\n" for line in kitti.label_lines(det_boxes, det_types,
                                                      np.zeros(len(det_boxes)), det_scores,
                                                      calib=kitti.SIM_CALIB)))
        ptypes = [kitti_type[synthetic.CLASS_NAMES[c]] for c in f.prop_classes]
        (proposals / f"{fid}.txt").write_text("".join(
            line + "\n" for line in kitti.label_lines(f.proposals, ptypes,
                                                      np.zeros(len(f.proposals)), f.prop_scores,
                                                      calib=kitti.SIM_CALIB)))
    return results, proposals


def test_kitti_label_round_trip(tmp_path):
    f = synthetic.synthetic_frame(n_points=2000, n_objects=30, n_proposals=10, seed=5)
    front = kitti.in_image(f.gt_boxes, calib=kitti.SIM_CALIB)
    lines = kitti.label_lines(f.gt_boxes, ["Car"] * 30, np.zeros(30), scores=np.arange(30) / 30,
                              calib=kitti.SIM_CALIB)
    (tmp_path / "a.txt").write_text(
        "".join(line + "\n" for line in lines)
        + "DontCare -1 -1 -10 1 2 3 4 -1 -1 -1 -1000 -1000 -1000 -10\n")
    boxes, names, scores = D.read_kitti_objects(tmp_path / "a.txt", kitti.SIM_CALIB, with_score=True)
    (tmp_path / "b.txt").write_text(lines[0].rsplit(" ", 1)[0] + "\n")  # no score column
    with pytest.raises(ValueError, match="16 columns"):
        D.read_kitti_objects(tmp_path / "b.txt", kitti.SIM_CALIB, with_score=True)
    assert front.sum() >= 3 and len(boxes) == front.sum() and names == ["car"] * len(boxes)
    np.testing.assert_allclose(scores, (np.arange(30) / 30)[front], atol=1e-4)
    ref = f.gt_boxes[front]
    np.testing.assert_allclose(boxes[:, :6], ref[:, :6], atol=0.011)
    dyaw = (boxes[:, 6] - ref[:, 6] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(dyaw, 0, atol=0.006)


def test_kitti_directory_dataset(tmp_path):
    frames = {"000000": synthetic.synthetic_frame(n_points=12_000, n_objects=14, n_proposals=120,
                                                  seed=21),
              "010000": synthetic.synthetic_frame(n_points=12_000, n_objects=14, n_proposals=120,
                                                  seed=22)}
    results, proposals = write_kitti(tmp_path, frames)
    data = D.load_kitti(tmp_path, results, settings(), proposals=proposals,
                        cache_dir=tmp_path / "cache", progress=False)
    for mode, ds in data.items():
        assert ds.n_frames == 2 and ds.groups == ["00", "01"]
        assert ds.frame_key.tolist() == ["000000", "010000"]
        for k, (fid, f) in enumerate(frames.items()):
            rows = np.flatnonzero(ds.frame == k)
            gt, names, _ = ds.gt_of(k)
            front = kitti.in_image(f.gt_boxes, calib=kitti.SIM_CALIB)
            assert len(gt) == front.sum() > 0
            np.testing.assert_allclose(gt[:, :6], f.gt_boxes[front][:, :6], atol=0.011)
            assert set(names.tolist()) <= set(CLASS_NAMES)
            # target = best BEV IoU with the labelled (front) boxes, as read back
            np.testing.assert_allclose(ds.iou_any[rows], iou_bev(ds.box[rows], gt).max(axis=1),
                                       atol=1e-12)
            if mode != "exact":  # result boxes as written (exact: NMS of the proposals)
                written = D.read_kitti_objects(results / f"{fid}.txt", kitti.SIM_CALIB,
                                                 with_score=True)[0]
                np.testing.assert_allclose(ds.box[rows], written[ds.det_index[rows]], atol=1e-12)
        assert ds.tp.any() and (~ds.tp).any()
        assert str(ds.frame_source[0]).endswith("training/velodyne/000000.bin")
    assert data["threshold"].X.shape[1] == 90 and data["none"].X.shape[1] == 17
    with pytest.raises(ValueError, match="need proposal files"):
        D.load_kitti(tmp_path, results, [D.settings_for("threshold")], progress=False)
    only_none = D.load_kitti(tmp_path, results, [D.settings_for("none")], frames=["010000"],
                             progress=False)["none"]
    assert only_none.frame_key.tolist() == ["010000"]
    np.testing.assert_array_equal(only_none.X, data["none"].X[data["none"].frame == 1])


def test_topic_options_read_a_bag_under_other_names(bag, tmp_path):
    """lmd-train / lmd-eval's --topic: a bag under a user's own topic names gives the
    rows of the same bag under the default names."""
    import argparse

    from realbags import user_named_copy

    path, _ = bag
    users = tmp_path / "users" / path.name
    topic_args = user_named_copy(path, users)
    ap = argparse.ArgumentParser()
    D.add_source_args(ap)
    ref = D.load_from_args(ap.parse_args(["--train", str(path), "--cache", ""]), settings(),
                           "train")
    args = ap.parse_args(["--train", str(users), "--cache", "", *topic_args])
    got = D.load_from_args(args, settings(), "train")
    for m in MODES:
        assert len(got[m].X) > 0
        np.testing.assert_array_equal(got[m].X, ref[m].X)
        np.testing.assert_array_equal(got[m].iou_any, ref[m].iou_any)
        assert list(got[m].det_id) == list(ref[m].det_id)
    with pytest.raises(ValueError, match="no topic /lidar/points"):    # without the options
        D.load_from_args(ap.parse_args(["--train", str(users), "--cache", ""]), settings(),
                         "train")
