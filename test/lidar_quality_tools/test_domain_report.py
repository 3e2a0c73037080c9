"""Domain report on small simulated sequences: the monitor quiet in the training domain and
at ERROR once scored for another detector's scores; adaptation rows for every labelled
frame count against the shipped pair and the detector score, evaluated on the test frames;
the acceptance table, the report and summary written."""
import json

import numpy as np
from lidar_quality_tools.domain_report import acceptance, main


def test_monitor_and_adaptation_on_small_sequences(tmp_path, capsys):
    out = tmp_path / "domain"
    assert main(["--out", str(out), "--test-sequences", "1", "--test-frames", "12",
                 "--pool-sequences", "3", "--pool-frames", "4", "--n-frames", "1,4,12",
                 "--draws", "2", "--columns", "1024", "--cases", "in domain,scores x 0.6",
                 "--kitti", str(tmp_path / "none"), "--held-out", "", "--methods", "lmd"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    rows = {r["case"]: r for r in summary["cases"]}
    assert set(rows) == {"in domain", "scores x 0.6"}          # no KITTI scans given
    assert rows["in domain"]["alarm_rate"] == 0.0
    assert rows["in domain"]["frames_to_error"] == [None]
    shifted = rows["scores x 0.6"]
    assert shifted["frames_to_error"][0] is not None and shifted["frames_to_error"][0] <= 12
    assert "score" in shifted["quantities"]
    for r in rows.values():
        a = r["adaptation"]
        assert set(a["adapted"]) == {"1", "4", "12"}            # JSON keys
        assert a["test"]["frames"] == 12 and a["test"]["boxes"] > 0
        for key in ("shipped", "detector score"):
            assert 0.5 < a[key]["auroc"] <= 1.0
        assert len(a["adapted"]["1"]["draws"]) == 2 and len(a["adapted"]["12"]["draws"]) == 1
        for e in a["adapted"].values():
            for d in e["draws"]:
                assert set(d["chosen"]) == {"classification", "regression"}
                assert 0.0 <= d["ece"] <= 1.0 and np.isfinite(d["r2"])
            assert e["mean"]["auroc"] == round(np.mean([d["auroc"] for d in e["draws"]]), 4)
        mon = a["adapted"]["12"]["draws"][0]["monitor"]
        assert mon["scored"] == 3 and 0 <= mon["alarms"] <= 3
    acc = summary["acceptance"]
    assert [a["case"] for a in acc] == []          # acceptance needs 20 labelled frames
    text = (out / "report.md").read_text()
    assert "| in domain | 12 | 0.0 % | never |" in text
    assert "| | adapted 4 |" in text and "| | only 12 |" in text
    assert "## LMS" not in text and "lms" not in summary
    assert "real KITTI scans not found" in capsys.readouterr().out


def test_acceptance_compares_with_the_detector_score():
    def case(name, auroc, ece, draws):
        return {"case": name, "adaptation": {
            "detector score": {"auroc": 0.9, "ece": 0.1},
            "adapted": {20: {"mean": {"auroc": auroc, "ece": ece}, "draws": draws}}}}

    rows = [case("in domain", 0.95, 0.05, []),
            case("a", 0.95, 0.05, [{"auroc": 0.95, "ece": 0.05}, {"auroc": 0.92, "ece": 0.08}]),
            case("b", 0.95, 0.05, [{"auroc": 0.95, "ece": 0.05}, {"auroc": 0.85, "ece": 0.05}]),
            case("c", 0.89, 0.05, [{"auroc": 0.89, "ece": 0.05}])]
    got = {a["case"]: (a["met_mean"], a["met_every_draw"]) for a in acceptance(rows)}
    assert got == {"a": (True, True), "b": (True, False), "c": (False, False)}


def test_lms_and_mimo_sections_on_tiny_bags(tmp_path, capsys):
    """LMS and MIMO only (``--methods``): perception bags per case, the nodes' monitors at
    ERROR once scored for another calibration, MIMO quiet in domain; adaptation rows against
    the shipped pair and the method's baseline; the report's sections and summary."""
    out = tmp_path / "domain"
    assert main(["--out", str(out), "--methods", "lms,mimo", "--columns", "1024",
                 "--lms-cases", "probabilities tempered (T = 2)",
                 "--mimo-cases", "in domain,head scores x 0.6",
                 "--lm-test-sequences", "1", "--lm-test-frames", "12",
                 "--lm-pool-sequences", "2", "--lm-pool-frames", "2", "--lm-n-frames", "1,4",
                 "--draws", "2", "--lms-train", "", "--held-out", ""]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cases"] == [] and summary["methods"] == ["lms", "mimo"]
    lms = {r["case"]: r for r in summary["lms"]["cases"]}
    mimo = {r["case"]: r for r in summary["mimo"]["cases"]}
    assert set(lms) == {"probabilities tempered (T = 2)"}
    assert set(mimo) == {"in domain", "head scores x 0.6"}
    assert summary["lms"]["sizes"]["n_frames"] == [1, 4]
    tempered = lms["probabilities tempered (T = 2)"]
    assert tempered["params"] == {"separate_probabilities": True, "width": 1024}
    assert tempered["frames"] == 12 and tempered["frames_to_error"][0] is not None
    assert mimo["in domain"]["alarm_rate"] == 0.0
    assert mimo["in domain"]["frames_to_error"] == [None]
    scaled = mimo["head scores x 0.6"]
    assert scaled["frames_to_error"][0] is not None and "score" in scaled["quantities"]
    for r, base in ((tempered, "entropy"), (mimo["in domain"], "merged score"),
                    (scaled, "merged score")):
        a = r["adaptation"]
        assert a["baseline_name"] == base and a["test"]["frames"] == 12
        assert a["pool_frames"] == 4 and set(a["adapted"]) == {"1", "4"}
        for key in ("shipped", "baseline"):
            assert 0.5 < a[key]["auroc"] <= 1.0 and 0.0 <= a[key]["ece"] <= 1.0
        assert (a["baseline"]["r2"] is None) == (base == "merged score")
        assert len(a["adapted"]["1"]["draws"]) == 2 and len(a["adapted"]["4"]["draws"]) == 1
        for e in a["adapted"].values():
            for d in e["draws"]:
                assert set(d["chosen"]) == {"classification", "regression"}
                assert 0.0 <= d["ece"] <= 1.0 and np.isfinite(d["r2"])
        mon = a["adapted"]["4"]["draws"][0]["monitor"]
        assert mon["scored"] == 3 and 0 <= mon["alarms"] <= 3
        assert len(a["frames only"]["4"]["draws"]) == 1
    assert tempered["adaptation"]["baseline"]["fitted_on"] == "the case's pool"
    text = (out / "report.md").read_text()
    assert "## LMS (LidarMetaSeg)" in text and "## MIMO (LiDAR-MIMO)" in text
    assert "## Adaptation (LMD)" not in text
    assert "| probabilities tempered (T = 2) | entropy |" in text
    assert "| in domain | 12 | 0.0 % | never |" in text
    assert "| head scores x 0.6 | merged score |" in text and "| | only 4 |" in text
    assert "real KITTI" not in capsys.readouterr().out       # LMD (and KITTI) not run
