"""lmd-eval end to end on tiny perception bags: report, PNGs and summary.json, with figures
that match a recomputation from the datasets (right columns, right targets)."""
import json

import numpy as np
import pytest
from lidar_quality_core import meta_model
from lidar_quality_core import metrics as M
from lmd_bags import write_split
from lidar_quality_training.lmd import dataset as D
from lidar_quality_training.lmd import evaluate as E
from sklearn.metrics import roc_auc_score


GREEDY = ["score", "n_proposals", "iou_bev_max", "prop_score_max", "points", "x", "l"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("lmd_eval")
    write_split(root / "meta_train", 3, 2, seed0=0)
    write_split(root / "meta_test", 2, 2, seed0=700)
    out, docs = root / "report", root / "docs" / "lmd_reliability.png"
    rc = E.main(["--train", str(root / "meta_train"), "--test", str(root / "meta_test"),
                 "--out", str(out), "--cache", str(root / "cache"), "--kinds", "xgboost",
                 "linear", "--cv-folds", "2", "--greedy-max", "2", "--greedy-rows", "0",
                 "--greedy-features", *GREEDY,
                 "--thumbnails", "2", "--review-k", "5", "10", "--docs-png", str(docs),
                 "--quiet"])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    sets = {part: D.load_bags([root / f"meta_{part}"], [D.settings_for("threshold")],
                              progress=False)["threshold"] for part in ("train", "test")}
    return out, docs, summary, sets


def test_report_files(run):
    out, docs, S, _ = run
    report = (out / "report.md").read_text()
    for heading in ("Held-out AUROC (Table I shape)", "Held-out R²", "Table II shape",
                    "Grouped 2-fold cross validation", "Calibration", "Greedy forward",
                    "Feature correlations", "Annotation-error proposals", "Acceptance"):
        assert heading in report
    for name in S["pngs"].values():
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({name})" in report
    assert docs.read_bytes() == (out / S["pngs"]["reliability"]).read_bytes()
    assert (out / "annotation_review" / "proposals_lmd_iou.csv").exists()
    assert (out / "annotation_review" / "proposals_score.json").exists()
    assert len(list((out / "annotation_review" / "thumbnails").glob("*.png"))) == 2
    assert set(S["modes"]) == {"exact", "threshold", "none"}
    assert set(S["held_out"]["threshold"]) == {"xgboost", "linear"}


def test_figures_match_a_recomputation(run):
    _, _, S, sets = run
    tr, te = sets["train"], sets["test"]
    assert S["data"]["test"]["boxes"] == len(te) and S["data"]["train"]["boxes"] == len(tr)
    # The detector score itself, checked against sklearn.
    assert S["detector_score"]["threshold"]["auroc"] == pytest.approx(
        roc_auc_score(te.tp, te.score))
    H = S["held_out"]["threshold"]
    for method, cols in (("score", ["score"]), ("box", list(E.BOX_FEATURES)),
                         ("lmd", list(te.feature_names))):
        clf = meta_model.fit_estimator("linear", "classification", tr.columns(cols),
                                       tr.tp.astype(float))
        reg = meta_model.fit_estimator("linear", "regression", tr.columns(cols), tr.iou)
        conf = meta_model.predict(clf, "classification", te.columns(cols))
        pred = np.clip(meta_model.predict(reg, "regression", te.columns(cols)), 0, 1)
        assert H["linear"][method]["classification"]["auroc"] == pytest.approx(
            roc_auc_score(te.tp, conf))
        assert H["linear"][method]["classification"]["ece"] == pytest.approx(M.ece(te.tp, conf))
        assert H["linear"][method]["regression"]["r2"] == pytest.approx(M.r2(te.iou, pred))
    # Table II row of the main mode = the Table I column of the same kind.
    assert S["modes"]["threshold"]["lmd"] == H["xgboost"]["lmd"]
    a = S["acceptance"]["threshold"]
    assert a["auroc"]["lmd"] == H["xgboost"]["lmd"]["classification"]["auroc"]
    assert a["ece_detector_score"] == S["detector_score"]["threshold"]["ece"]
    corr = dict((n, r) for n, r in S["correlations"])
    assert corr["score"] == pytest.approx(np.corrcoef(te.score, te.iou)[0, 1])
    g = S["greedy"]["classification"]
    assert 1 <= len(g["selected"]) <= 2 and g["rows"] == len(tr)
    assert set(g["selected"]) <= set(GREEDY) and g["candidates"] == len(GREEDY)
    assert all(b >= a_ for a_, b in zip(g["scores"], g["scores"][1:]))
    cv = S["cv"]["xgboost"]["lmd"]["regression"]["r2"]
    assert len(cv) == 2 and np.isfinite(cv[0])
    R = S["annotation_review"]
    assert R["fp_total"] == int((R["fp_total"])) > 0
    assert set(R["precision_at_k"]) == {"lmd_iou", "lmd_confidence", "score", "random"}
