"""Result tables (``process_bag --results``) on a simulated perception bag with ground
truth: one row per scored detection / kept segment, the values the output bag carries,
the features the models were given, targets computed from the bag's ground truth."""
import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.conventions import TP_IOU
from lidar_quality_core.detection_eval import match_frame
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_ros.bag_io import read_bag
from lidar_quality_tools.process import main
from lidar_quality_tools.result_tables import BOX_COLUMNS, FEATURE_PREFIX
from lmd_ros.pipeline import LmdSettings, default_model_paths
from perception_bags import simulated_perception_bags
from reference_perception.cli import Perception


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    bags = simulated_perception_bags(root, Perception(heads=2), n_sequences=1, n_frames=2,
                                     seed=11, columns=512)
    out, res = root / "out", root / "res"
    assert main(["--bag", str(bags / "seq_00"), "--out", str(out), "--results", str(res),
                 "--no-progress"]) == 0
    tables = {n: pq.read_table(res / n / "bag=seq_00" / "part-0000.parquet")
              for n in ("lmd", "lms", "mimo")}
    return bags / "seq_00", out, tables, res


def quality(out, topic):
    return [m.decode() for m in read_bag(out, {topic})]


def meta(table):
    return {k.decode(): v.decode() for k, v in table.schema.metadata.items()}


def test_lmd_rows_are_the_quality_messages_and_the_models_features(run):
    bag, out, tables, _ = run
    t = tables["lmd"].to_pandas()
    q = [(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, d) for m in
         quality(out, "/lmd/output/quality") for d in m.detections]
    assert len(t) == len(q) > 0
    assert t["frame_key"].tolist() == [str(s) for s, _ in q]
    assert t["index"].tolist() == [d.detection_index for _, d in q]
    assert t["det_id"].tolist() == [d.detection_id for _, d in q]
    assert np.allclose(t["confidence"], [d.confidence for _, d in q], equal_nan=True)
    assert np.allclose(t["score"], [d.original_score for _, d in q])
    assert_drift_columns(t, quality(out, "/lmd/output/quality"), "detections")
    assert_drift_columns(tables["mimo"].to_pandas(), quality(out, "/mimo/output/uncertainty"),
                         "clusters")
    m = meta(tables["lmd"])
    names = json.loads(m["lq.feature_names"])
    assert names == list(LmdSettings().feature_names())
    assert m["lq.method"] == "lmd" and m["lq.mode"] == "threshold"
    models = MetaModels(*default_model_paths("threshold"), names)
    X = t[[FEATURE_PREFIX + n for n in names]].to_numpy()
    conf, iou = models.predict(X)
    assert np.allclose(conf, t["confidence"], equal_nan=True)
    assert np.allclose(iou, t["predicted_iou"], equal_nan=True)


def assert_drift_columns(t, msgs, items):
    """Each row's drift columns are its frame's quality message's verdict."""
    rows = [(m.drift_level, m.drift_score, m.passthrough, type(m))
            for m in msgs for _ in getattr(m, items)]
    assert len(rows) == len(t) > 0
    names = {"DRIFT_OFF": "off", "DRIFT_WARMING_UP": "warming up", "DRIFT_OK": "OK",
             "DRIFT_WARN": "WARN", "DRIFT_ERROR": "ERROR"}
    assert t["drift_level"].tolist() == [
        next(n for c, n in names.items() if getattr(cls, c) == level)
        for level, _, _, cls in rows]
    assert np.allclose(t["drift_score"], [s for _, s, _, _ in rows], equal_nan=True)
    assert t["passthrough"].tolist() == [p for _, _, p, _ in rows]
    # the shipped models record their training profile: two frames are a window too short
    assert set(t["drift_level"]) == {"warming up"} and t["drift_score"].isna().all()


def test_box_targets_from_the_ground_truth(run):
    bag, out, tables, _ = run
    gt = {m.stamp_ns: m.decode() for m in read_bag(bag, {"/lidar/gt_objects"})}
    gt = {str(g.header.stamp.sec * 10**9 + g.header.stamp.nanosec): detections_to_arrays(g)
          for g in gt.values()}
    for node in ("lmd", "mimo"):
        t = tables[node].to_pandas()
        assert t["iou_any"].notna().all() and (t["iou_any"] > 0.5).any()
        for key, rows in t.groupby("frame_key"):
            g = gt[key]
            m = match_frame(rows[list(BOX_COLUMNS)].to_numpy(), rows["score"].to_numpy(),
                            rows["label"].tolist(), g.boxes[g.valid],
                            [c for c, v in zip(g.labels, g.valid) if v], iou_threshold=TP_IOU)
            assert np.allclose(m.iou_any, rows["iou_any"]), node
            assert np.allclose(m.iou_same_class, rows["iou_class"]), node


def test_lms_rows_are_the_segment_messages_with_targets(run):
    bag, out, tables, _ = run
    t = tables["lms"].to_pandas()
    segs = [s for m in quality(out, "/lms/output/segments") for s in m.segments
            if np.isfinite(s.confidence)]
    assert len(t) == len(segs) > 0
    assert t["index"].tolist() == [s.segment_id for s in segs]
    assert t["label"].tolist() == [s.class_name for s in segs]
    assert np.allclose(t["confidence"], [s.confidence for s in segs])
    assert np.allclose(t["predicted_iou"], [s.predicted_iou for s in segs])
    assert t["iou_adj"].between(0, 1).all() and t["iou"].between(0, 1).all()
    msgs = quality(out, "/lms/output/segments")
    for m in msgs:     # the table keeps the scored segments only
        m.segments = [s for s in m.segments if np.isfinite(s.confidence)]
    assert_drift_columns(t, msgs, "segments")
    names = json.loads(meta(tables["lms"])["lq.feature_names"])
    assert [c for c in t.columns if c.startswith(FEATURE_PREFIX)] == \
        [FEATURE_PREFIX + n for n in names]


def test_bag_without_ground_truth_gives_nan_targets(run, tmp_path):
    from lidar_quality_ros.bag_io import BagWriter, bag_info

    bag, _, _, _ = run
    info = bag_info(bag)
    stripped = tmp_path / "no_gt"
    with BagWriter(stripped) as w:
        for m in read_bag(bag):
            if m.topic not in ("/lidar/gt_objects", "/lidar/points_gt"):
                t = info.topics[m.topic]
                w.write(m.topic, m.msgtype, m.stamp_ns, m.raw, qos=t.qos, source=t)
    res = tmp_path / "res"
    assert main(["--bag", str(stripped), "--out", str(tmp_path / "out"), "--results", str(res),
                 "--no-progress", "--nodes", "lmd,lms"]) == 0
    lmd = pq.read_table(res / "lmd" / "bag=no_gt" / "part-0000.parquet").to_pandas()
    lms = pq.read_table(res / "lms" / "bag=no_gt" / "part-0000.parquet").to_pandas()
    assert len(lmd) and lmd["iou_any"].isna().all() and lmd["confidence"].notna().any()
    assert len(lms) and lms["iou_adj"].isna().all()


def test_tables_read_back_as_the_dataset_builders_rows(run):
    """The table of a labelled bag is training data: read by ``feature_table`` it gives the
    rows, features and targets the LMD / MIMO dataset builders compute from the bag."""
    from lidar_quality_training.feature_table import read_lmd, read_mimo
    from lidar_quality_training.lmd.dataset import load_bags, settings_for
    from lidar_quality_training.mimo.dataset import load_bags as load_mimo

    bag, _, _, res = run
    table = read_lmd([res / "lmd"])["threshold"]
    built = load_bags([bag], [settings_for("threshold")], progress=False)["threshold"]
    assert len(table) == len(built) > 0
    assert np.array_equal(table.X, built.X, equal_nan=True)
    assert np.allclose(table.iou_any, built.iou_any) and np.allclose(table.score, built.score)
    assert table.group.tolist() == built.group.tolist()
    mimo = read_mimo([res / "mimo"])
    built = load_mimo([bag], progress=False)
    assert len(mimo) == len(built) > 0
    assert np.allclose(mimo.m_iou_any, built.m_iou_any)
    assert np.allclose(mimo.X, built.X[:, :mimo.X.shape[1]], equal_nan=True)


def test_unusable_ground_truth_is_said_once_and_counted(run, tmp_path, capsys):
    """A ground-truth cloud that does not label the segmented cloud (another point count):
    LMS targets NaN, one warning naming the topic, every frame counted."""
    from lidar_quality_core.pointcloud import create_cloud
    from lidar_quality_ros.bag_io import BagWriter, bag_info

    bag, _, _, _ = run
    info = bag_info(bag)
    other = tmp_path / "short_gt"
    with BagWriter(other) as w:
        for m in read_bag(bag):
            t = info.topics[m.topic]
            if m.topic == "/lidar/points_gt":
                gt = m.decode()
                short = create_cloud(gt.header, {"x": np.zeros(10, np.float32),
                                                 "y": np.zeros(10, np.float32),
                                                 "z": np.zeros(10, np.float32),
                                                 "label": np.ones(10, np.uint32)})
                w.write(m.topic, m.msgtype, m.stamp_ns, short, qos=t.qos)
            else:
                w.write(m.topic, m.msgtype, m.stamp_ns, m.raw, qos=t.qos, source=t)
    from lidar_quality_tools.process import process_bag

    res = tmp_path / "res"
    s = process_bag(other, tmp_path / "out", nodes="lms", progress=False, results=res)
    err = capsys.readouterr().err
    assert err.count("/lidar/points_gt does not label the segmented cloud") == 1
    assert s["results_issues"] == {"points_gt_mismatch": 2}          # both frames
    lms = pq.read_table(res / "lms" / "bag=short_gt" / "part-0000.parquet").to_pandas()
    assert len(lms) and lms["iou_adj"].isna().all() and lms["confidence"].notna().any()
