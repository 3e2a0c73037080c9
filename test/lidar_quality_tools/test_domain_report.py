"""Domain report on small simulated sequences: quiet in the training domain, an ERROR
once scored for another detector's scores, the report and summary written."""
import json

from lidar_quality_tools.domain_report import main


def test_quiet_in_domain_and_fires_on_another_detector(tmp_path, capsys):
    out = tmp_path / "domain"
    assert main(["--out", str(out), "--sequences", "1", "--frames", "12", "--columns", "1024",
                 "--cases", "in domain,scores x 0.6", "--kitti", str(tmp_path / "none")]) == 0
    rows = {r["case"]: r for r in json.loads((out / "summary.json").read_text())}
    assert set(rows) == {"in domain", "scores x 0.6"}          # no KITTI scans given
    assert rows["in domain"]["alarm_rate"] == 0.0
    assert rows["in domain"]["frames_to_error"] == [None]
    shifted = rows["scores x 0.6"]
    assert shifted["frames_to_error"][0] is not None and shifted["frames_to_error"][0] <= 12
    assert "score" in shifted["quantities"]
    text = (out / "report.md").read_text()
    assert "| in domain | 12 | 0.0 % | never |" in text
    assert "real KITTI scans not found" in capsys.readouterr().out
