"""lidar_quality_training.lmd.annotation_review: FP ranking and precision@k on a hand-built case with known
answers, seeded error injection, exports, thumbnails, cloud loading from a bag."""
import csv
import json

import numpy as np
import pytest
from lidar_quality_core.iou import iou_bev
from lidar_sim.annotation_errors import AnnotationErrorConfig, apply_records
from lmd_bags import write_bag
from lidar_quality_training.lmd import annotation_review as AR
from lidar_quality_training.lmd.dataset import LmdDataset

CAR = [4.5, 1.8, 1.5]


def car(x, y, yaw=0.0):
    return [x, y, -1.0, *CAR, yaw]


def make_ds(frames):
    """LmdDataset from ``[(gt boxes, gt labels, gt points, det boxes, det scores), ...]``;
    targets computed here (best BEV IoU, any class)."""
    rows = {k: [] for k in ("box", "score", "frame", "iou")}
    gt_box, gt_label, gt_pts, offsets = [], [], [], [0]
    for k, (gb, gl, gp, db, sc) in enumerate(frames):
        gb, db = np.asarray(gb, float).reshape(-1, 7), np.asarray(db, float).reshape(-1, 7)
        rows["box"].append(db)
        rows["score"].append(np.asarray(sc, float))
        rows["frame"].append(np.full(len(db), k))
        rows["iou"].append(iou_bev(db, gb).max(axis=1, initial=0.0))
        gt_box.append(gb)
        gt_label += list(gl)
        gt_pts += list(gp)
        offsets.append(offsets[-1] + len(gb))
    box = np.concatenate(rows["box"])
    n = len(box)
    iou = np.concatenate(rows["iou"])
    nf = len(frames)
    return LmdDataset(
        mode="none", feature_names=("score",), X=np.concatenate(rows["score"])[:, None],
        iou_any=iou, iou_class=iou, score=np.concatenate(rows["score"]),
        label=np.array(["car"] * n), box=box, det_index=np.arange(n),
        det_id=np.array([f"d{i}" for i in range(n)]), frame=np.concatenate(rows["frame"]),
        frame_group=np.array([f"g{k}" for k in range(nf)]),
        frame_source=np.array([f"src{k}" for k in range(nf)]),
        frame_key=np.array([str(k) for k in range(nf)]), frame_points=np.full(nf, 1000),
        gt_offsets=np.array(offsets), gt_box=np.concatenate(gt_box),
        gt_label=np.array(gt_label), gt_id=np.array([str(i) for i in range(len(gt_label))]),
        gt_points=np.array(gt_pts))


@pytest.fixture
def case():
    """Frame 0: GT A, B, C; frame 1: GT D. Detections d0 = A, d1 = B, d2 background,
    d3 = C moved 2 m back (IoU 0.38), d4 = D, d5 background. Given labels: B missing,
    C shifted 3 m forward, D shrunk to half length and width."""
    A, B, C, D = car(10, 0), car(0, 10), car(-10, 0), car(20, 5)
    ds = make_ds([([A, B, C], ["car"] * 3, [50, 40, 30], [A, B, car(30, 30), car(-12, 0)],
                   [0.8, 0.3, 0.95, 0.5]),
                  ([D], ["car"], [20], [D, car(-30, -30)], [0.2, 0.9])])
    recs0 = [{"kind": "missing", "instance": 1}, {"kind": "shifted", "instance": 2,
                                                  "dx": 3.0, "dy": 0.0}]
    recs1 = [{"kind": "resized", "instance": 0, "scale_lwh": [0.5, 0.5, 1.0]}]
    g0 = apply_records(recs0, [A, B, C], np.zeros(3), np.arange(3))[0]
    g1 = apply_records(recs1, [D], np.zeros(1), np.arange(1))[0]
    errors = AR.InjectedErrors(
        gt_offsets=np.array([0, len(g0), len(g0) + len(g1)]), gt_box=np.concatenate([g0, g1]),
        gt_label=np.array(["car"] * (len(g0) + len(g1))),
        records=[{"frame": 0, **r} for r in recs0] + [{"frame": 1, **r} for r in recs1],
        corrupted=np.array([False, True, True, True]),
        kinds={1: ["missing"], 2: ["shifted"], 3: ["resized"]})
    pred_iou = np.array([0.95, 0.9, 0.2, 0.7, 0.8, 0.1])
    conf = np.array([0.99, 0.6, 0.1, 0.95, 0.5, 0.3])
    return ds, errors, conf, pred_iou


def test_hand_built_ranking_and_precision(case):
    ds, errors, conf, pred_iou = case
    assert ds.iou[3] == pytest.approx(2.5 / 6.5)  # d3 vs clean C: 2.5 m of 4.5 overlap
    res = AR.review(ds, conf, pred_iou, errors=errors, ks=(2, 4), seed=1)
    given = res.given_iou
    np.testing.assert_allclose(given, [1, 0, 0, 0, 0.25, 0], atol=1e-9)
    assert res.fp_rows.tolist() == [1, 2, 3, 4, 5]
    assert res.order["lmd_iou"].tolist() == [1, 4, 3, 2, 5]
    assert res.order["lmd_confidence"].tolist() == [3, 1, 4, 5, 2]
    assert res.order["score"].tolist() == [2, 5, 3, 1, 4]
    assert sorted(res.order["random"].tolist()) == [1, 2, 3, 4, 5]
    assert np.flatnonzero(res.hits["caused"]).tolist() == [1, 4]     # B missing, D resized
    assert np.flatnonzero(res.hits["near"]).tolist() == [1, 3, 4]    # + d3 at shifted C
    p = res.precision
    assert p["lmd_iou"]["caused"] == {2: 1.0, 4: 0.5}
    assert p["lmd_iou"]["near"] == {2: 1.0, 4: 0.75}
    assert p["lmd_confidence"]["caused"] == {2: 0.5, 4: 0.5}
    assert p["score"]["caused"] == {2: 0.0, 4: 0.25}
    assert res.expected_random == {"caused": 0.4, "near": 0.6}
    s = AR.summary(res, errors)
    assert s["fp_total"] == 5 and s["hits_among_fps"] == {"caused": 2, "near": 3}
    assert s["errors_injected"] == {"missing": 1, "shifted": 1, "resized": 1}
    # Without errors: FPs against the dataset's own labels, no precision.
    plain = AR.review(ds, conf, pred_iou)
    assert plain.fp_rows.tolist() == [2, 3, 5] and plain.precision == {}
    assert plain.order["lmd_iou"].tolist() == [3, 2, 5]


def test_export_and_thumbnails(case, tmp_path):
    ds, errors, conf, pred_iou = case
    res = AR.review(ds, conf, pred_iou, errors=errors, ks=(2,))
    cpath, jpath = AR.export(ds, res, conf, pred_iou, tmp_path, k=3)
    with open(cpath) as f:
        table = list(csv.DictReader(f))
    assert [r["detection_id"] for r in table] == ["d1", "d4", "d3"]
    assert [float(r["predicted_iou"]) for r in table] == [0.9, 0.8, 0.7]
    assert [r["hit_caused"] for r in table] == ["True", "True", "False"]
    assert float(table[1]["x"]) == 20 and table[1]["group"] == "g1" and table[0]["class"] == "car"
    js = json.loads(jpath.read_text())
    assert js["fp_total"] == 5 and [r["rank"] for r in js["proposals"]] == [1, 2, 3]
    assert js["proposals"][2]["confidence"] == 0.95
    calls = []

    def points(source, key):
        calls.append((source, key))
        rng = np.random.default_rng(int(key))
        return rng.uniform(-40, 40, (500, 3))

    paths = AR.thumbnails(ds, res, conf, pred_iou, tmp_path, k=3, errors=errors, points=points)
    assert len(paths) == 4 and paths[-1].name == "sheet_lmd_iou.png"
    assert sorted(calls) == [("src0", "0"), ("src1", "1")]  # one load per frame
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_injection_is_seeded_and_only_touches_visible_boxes():
    rng = np.random.default_rng(0)
    frames = []
    for k in range(6):
        gb = [car(x, y) for x, y in rng.uniform(-50, 50, (10, 2))]
        pts = rng.integers(0, 3, 10)  # some boxes without points
        frames.append((gb, ["car", "truck"] * 5, pts, gb[:1], [0.5]))
    ds = make_ds(frames)
    cfg = AnnotationErrorConfig(p_missing=0.3, p_shift=0.3, p_resize=0.3, p_wrong_class=0.3)
    a = AR.inject_errors(ds, seed=4, config=cfg)
    b = AR.inject_errors(ds, seed=4, config=cfg)
    c = AR.inject_errors(ds, seed=5, config=cfg)
    assert a.records == b.records and a.records != c.records
    np.testing.assert_array_equal(a.gt_box, b.gt_box)
    assert not a.corrupted[ds.gt_points == 0].any() and a.corrupted.sum() > 5
    assert set(a.counts()) == {"missing", "shifted", "resized", "wrong_class"}
    assert len(a.gt_box) == len(ds.gt_box) - a.counts()["missing"]
    for k in range(ds.n_frames):
        lo, hi = ds.gt_offsets[k], ds.gt_offsets[k + 1]
        given = a.gt_box[a.gt_offsets[k]:a.gt_offsets[k + 1]]
        untouched = ds.gt_box[lo:hi][~a.corrupted[lo:hi]]
        # every uncorrupted box is in the given labels unchanged
        for bx in untouched:
            assert np.any(np.all(given == bx, axis=1))
    wrong = [r for r in a.records if r["kind"] == "wrong_class"]
    assert all({r["from_class"], r["to_class"]} in ({10, 11},) for r in wrong)  # car <-> truck


def test_load_points_from_bag(tmp_path):
    from lidar_quality_core.pointcloud import xyz_intensity

    frames = write_bag(tmp_path / "bag", [1, 2, 3])
    f, (cloud, *_), stamp = frames[1]
    xyz = AR.load_points(str(tmp_path / "bag"), str(stamp))
    np.testing.assert_array_equal(xyz, xyz_intensity(cloud)[0])
    with pytest.raises(KeyError, match="no /lidar/points message"):
        AR.load_points(str(tmp_path / "bag"), "123")


def test_cli_with_models_and_injected_errors(tmp_path, monkeypatch):
    """``python -m lidar_quality_training.lmd.annotation_review`` on a tiny bag with real (small) models: the
    summary's precision@k is the one of ``review`` on the models' own predictions."""
    from lidar_quality_core.meta_model import MetaModels
    from lmd_frames import train_models
    from lidar_quality_training.lmd.dataset import load_bags, settings_for

    settings = settings_for("threshold")
    train_models(tmp_path / "models", settings, n_frames=3)
    write_bag(tmp_path / "bags" / "seq_00", [31, 32, 33])
    out = tmp_path / "review"
    monkeypatch.chdir(tmp_path)  # a cache would land in ./out/lmd/cache
    assert AR.main(["--test", str(tmp_path / "bags"), "--mode", "threshold", "--models",
                    str(tmp_path / "models"), "--out", str(out), "--inject-errors", "--seed", "2",
                    "--k", "3", "5", "--thumbnails", "2", "--cache", "", "--quiet"]) == 0
    S = json.loads((out / "summary.json").read_text())
    ds = load_bags([tmp_path / "bags"], [settings], progress=False)["threshold"]
    models = MetaModels(tmp_path / "models" / "lmd_threshold_classifier.joblib",
                        tmp_path / "models" / "lmd_threshold_regressor.joblib",
                        settings.feature_names())
    conf, iou = models.predict(ds.X)
    errors = AR.inject_errors(ds, seed=2)
    res = AR.review(ds, conf, iou, errors=errors, ks=(3, 5), seed=2)
    assert S == json.loads(json.dumps(AR.summary(res, errors)))
    table = json.loads((out / "proposals_lmd_iou.json").read_text())["proposals"]
    assert [r["row"] for r in table] == res.order["lmd_iou"][:5].tolist()
    assert (out / "proposals_score.csv").exists() and (out / "sheet_lmd_iou.png").exists()
    assert not (tmp_path / "out").exists()  # --cache '': none written
