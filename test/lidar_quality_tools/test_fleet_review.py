"""Fleet review over the result tables of two simulated bags with ground truth: both lists
ranked as documented across the bags, thumbnails and the report; bags without ground
truth give no annotation-error candidates and say why."""
import numpy as np
import pandas as pd
import pytest
from lidar_quality_core.conventions import TP_IOU
from lidar_quality_tools.fleet_review import load_results, main, review
from lidar_quality_tools.process import process_bag
from perception_bags import simulated_perception_bags
from reference_perception.cli import Perception


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("review")
    bags = simulated_perception_bags(root, Perception(), n_sequences=2, n_frames=2, seed=8,
                                     columns=512)
    res = root / "results"
    for b in sorted(bags.iterdir()):
        process_bag(b, root / "out" / b.name, nodes="lmd", progress=False, results=res)
    return res


def test_lists_are_ranked_over_every_bag(results, tmp_path):
    df = load_results(results)
    assert set(df["bag"]) == {"seq_00", "seq_01"}
    lists = review(results, k=15, n_thumbnails=3)
    err, weak = lists["annotation_errors"], lists["low_confidence"]
    fp = df[df["valid"] & (df["iou_any"] < TP_IOU)]
    assert len(err) == min(15, len(fp)) > 0
    assert (err["iou_any"] < TP_IOU).all()
    assert np.all(np.diff(err["predicted_iou"]) <= 0)
    assert err["predicted_iou"].iloc[0] == fp["predicted_iou"].max()
    assert weak["kept"].all() and np.all(np.diff(weak["confidence"]) >= 0)
    assert weak["confidence"].iloc[0] == df[df["kept"]]["confidence"].min()
    rdir = results / "review"
    csv = pd.read_csv(rdir / "annotation_errors.csv")
    assert csv["rank"].tolist() == list(range(1, len(err) + 1))
    for name in ("annotation_errors", "low_confidence"):
        assert len(list((rdir / "thumbnails").glob(f"{name}_*.png"))) == 3
        assert (rdir / f"sheet_{name}.png").stat().st_size > 10_000
    report = (rdir / "report.md").read_text()
    assert f"{len(df)} detections of 2 bag(s)" in report and "| rank | bag |" in report


def test_without_ground_truth_the_report_says_so(results, tmp_path):
    df = load_results(results)
    df["iou_any"] = np.nan
    part = tmp_path / "results" / "lmd" / "bag=x"
    part.mkdir(parents=True)
    df.drop(columns="bag").to_parquet(part / "part-0000.parquet")
    assert main([str(tmp_path), "--thumbnails", "0"]) == 0
    assert len(pd.read_csv(tmp_path / "review" / "annotation_errors.csv")) == 0
    assert "No bag has ground truth" in (tmp_path / "review" / "report.md").read_text()
    assert main([str(tmp_path / "nothing")]) == 2
